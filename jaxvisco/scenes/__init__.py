"""Built-in scenes."""

from ._lshape import lshape as lshape
