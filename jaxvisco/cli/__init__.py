"""Command line: ``jaxvisco paper | run | plot | scene-template`` (the parser and `main`
are in `_main`, each subcommand in a module of its own)."""

from ._main import main as main
