"""The command line, ``clrf train | render | eval | view | export | devices | bench | process``:
main.py (the parser and the train / render / devices / bench commands), config_flags.py
(--SECTION.KEY flags), evaluate.py, export.py, process.py (their commands) and common.py
(what the commands share)."""
from .main import main

__all__ = ["main"]
