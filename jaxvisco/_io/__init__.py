"""Results files: HDF5 with a crash-consistent commit, an XDMF sidecar, verified restarts."""

from ._layout import scene_attributes as scene_attributes
from ._read import Restart as Restart
from ._read import read_restart as read_restart
from ._read import read_results as read_results
from ._writer import ResultsWriter as ResultsWriter
from ._writer import save as save
from ._xdmf import write_xdmf as write_xdmf
