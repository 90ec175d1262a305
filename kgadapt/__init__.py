"""kgadapt: robot software that knows itself at run time (the command lives in kgadapt.cli)."""

__version__ = "0.1.0"
