"""The XDMF time series beside a results file, for ParaView.

``name.xdmf`` is a temporal collection whose grids reference the HDF5 datasets by
relative path, so the pair can be moved together. It lists committed frames only: it
is extended after each commit (one ``write`` of the new grids plus the closing tags, so
its cost does not grow with the run) and rewritten whole when a file is reopened.

Why per-frame datasets rather than slices of ``/nodal/x``: ParaView's Xdmf3 readers
(``Xdmf3ReaderS``/``T``, ParaView 5.11) crash (SIGSEGV in CopyShape) on a HyperSlab
geometry and read no points from a ``Function`` geometry; plain datasets, one per
frame, open in the legacy ``XDMFReader`` and both Xdmf3 readers (tested in
tests/test_results.py when ``pvpython`` is installed). ParaView treats only
3-component point data as vectors (glyphs, warp by vector), so geometry, displacement
and momentum are padded to 3 components in 2D. Known ParaView quirk: the Xdmf3 readers
resolve the relative HDF5 path wrongly when the XDMF file name has no directory part
(``pvpython`` with ``r.xdmf``); pass ``./r.xdmf`` or an absolute path.
"""

import os
from xml.sax.saxutils import escape

import numpy as np

from ._layout import committed, frame_name

XDMF_TOPOLOGY = {
    "tri3": "Triangle", "tri6": "Triangle_6", "quad4": "Quadrilateral", "quad8": "Quadrilateral_8",
    "quad9": "Quadrilateral_9", "tet4": "Tetrahedron", "tet10": "Tetrahedron_10", "hex8": "Hexahedron",
    "hex20": "Hexahedron_20", "hex27": "Hexahedron_27",
}
_HEAD = ('<?xml version="1.0"?>\n<Xdmf Version="3.0" xmlns:xi="http://www.w3.org/2001/XInclude">\n'
         '  <Domain>\n  <Grid Name="TimeSeries" GridType="Collection" CollectionType="Temporal">\n')
_TAIL = '  </Grid>\n  </Domain>\n</Xdmf>\n'


def pad3(a):
    """Zero-pad the last axis to 3 components."""
    a = np.asarray(a, dtype=np.float64)
    return np.concatenate([a, np.zeros(a.shape[:-1] + (3 - a.shape[-1],))], axis=-1) if a.shape[-1] < 3 else a


def _grids(xdmf_path, h5_path, f, start, stop):
    """XML of the grids of frames start..stop-1 (reading times and sizes from `f`)."""
    times = np.asarray(f["time"][start:stop]) if "time" in f else np.zeros(0)
    N = f["mesh/points"].shape[0]
    cells = f["mesh/cells"]
    nc, nn = cells.shape
    ctype = str(cells.attrs["cell_type"])
    topo = XDMF_TOPOLOGY.get(ctype)
    if topo is None:
        raise ValueError(f"no XDMF topology for cell type {ctype!r}; known: {sorted(XDMF_TOPOLOGY)}.")
    rel = escape(os.path.relpath(os.path.abspath(h5_path), os.path.dirname(os.path.abspath(xdmf_path))))

    def item(path):
        return (f'<DataItem Dimensions="{N} 3" NumberType="Float" Precision="8" Format="HDF">'
                f'{rel}:{path}</DataItem>')

    out = []
    for j, t in enumerate(times):
        name = frame_name(start + j)
        out.append(
            f'    <Grid Name="frame{name}" GridType="Uniform">\n'
            f'      <Time Value="{float(t):.17g}"/>\n'
            f'      <Topology TopologyType="{topo}" NumberOfElements="{nc}" NodesPerElement="{nn}">\n'
            f'        <DataItem Dimensions="{nc} {nn}" NumberType="Int" Precision="8" Format="HDF">'
            f'{rel}:/mesh/cells</DataItem>\n      </Topology>\n'
            f'      <Geometry GeometryType="XYZ">\n        {item("/xdmf/geometry/" + name)}\n      </Geometry>\n'
            f'      <Attribute Name="displacement" AttributeType="Vector" Center="Node">\n'
            f'        {item("/xdmf/displacement/" + name)}\n      </Attribute>\n'
            f'      <Attribute Name="momentum" AttributeType="Vector" Center="Node">\n'
            f'        {item("/xdmf/momentum/" + name)}\n      </Attribute>\n'
            f'    </Grid>\n')
    return "".join(out)


def extend_xdmf(xdmf_path, h5_path, f, start, stop):
    """Add the grids of frames start..stop-1 to an XDMF file written by this module, in
    one `write` that replaces the closing tags (else rewrite the file)."""
    tail = _TAIL.encode()
    try:
        with open(xdmf_path, "r+b") as fh:
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            fh.seek(max(0, size - len(tail)))
            if fh.read() == tail:
                fh.seek(size - len(tail))
                fh.write((_grids(xdmf_path, h5_path, f, start, stop) + _TAIL).encode())
                return
    except FileNotFoundError:
        pass
    write_xdmf(xdmf_path, h5_path, f)


def write_xdmf(xdmf_path, h5_path, f=None):
    """Write an XDMF 3 temporal collection of the committed frames of `h5_path`.

    The HDF5 file is referenced by its path relative to the XDMF file. `f`: an open
    h5py file (read from `h5_path` if None). The file is replaced atomically.
    """
    own = f is None
    if own:
        import h5py

        f = h5py.File(h5_path, "r")
    try:
        xml = _HEAD + _grids(xdmf_path, h5_path, f, 0, committed(f).n_frames) + _TAIL
    finally:
        if own:
            f.close()
    tmp = xdmf_path + ".tmp"
    with open(tmp, "w") as fh:
        fh.write(xml)
    os.replace(tmp, xdmf_path)
