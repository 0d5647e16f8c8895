"""The package version, in a module of its own so that any layer can read it without importing
the package's public facade (``torchmcmcpf/__init__``, the top layer; see ``tests/test_layers.py``).
``pyproject.toml`` reads it from here.
"""

__version__ = "0.2.0"
