"""Notebooks run under ``pytest --nbmake`` in quick mode: the kernel inherits this variable."""

import os

os.environ.setdefault("TORCHMCMCPF_QUICK", "1")
