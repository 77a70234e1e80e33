"""Command line: ``jaxvisco paper | run | plot | scene-template`` (the code is in `_main`)."""

from ._main import main as main
