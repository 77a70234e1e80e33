"""Built-in scenes."""

from ._lshape import PAPER as PAPER
from ._lshape import lshape as lshape
