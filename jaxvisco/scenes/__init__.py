"""Built-in scenes."""

from ._lshape import PAPER as PAPER
from ._lshape import lshape as lshape
from ._specimen import POLYMER as POLYMER
from ._specimen import Specimen as Specimen
from ._specimen import specimen as specimen
