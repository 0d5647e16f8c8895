"""Notebooks run under ``pytest --nbmake`` in quick mode: the kernel inherits these variables.

``TORCHMCMCPF_OUT`` sends whatever a notebook writes to a temporary folder, so the test run
leaves nothing in the working tree (a notebook opened by hand writes to ``results/``).
"""

import atexit
import os
import shutil
import tempfile

os.environ.setdefault("TORCHMCMCPF_QUICK", "1")
if "TORCHMCMCPF_OUT" not in os.environ:
    _out = tempfile.mkdtemp(prefix="torchmcmcpf-notebooks-")
    os.environ["TORCHMCMCPF_OUT"] = _out
    atexit.register(shutil.rmtree, _out, ignore_errors=True)
