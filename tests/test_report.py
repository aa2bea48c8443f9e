"""Pieces of the fit report: fields in the mesh file's node order, the XDMF series, the skin read
from the model files."""
import pathlib

import h5py
import numpy as np
import pytest
from mpi4py import MPI
from dolfinx import fem

from face_dolfinx.results.xdmf import FileNodeOrder, XdmfSeries
from face_dolfinx.results.report import frame_ranges


def test_file_node_order_gathers_and_scatters_exactly(model, builtin_model_path):
    """Gathered in file order, the dof coordinates are the file's nodes, on any number of ranks;
    scattered back, a field is the same local array, ghosts included."""
    space = fem.VectorFunctionSpace(model.mesh, ("CG", 1))
    order = FileNodeOrder(space)
    gathered = order.gather(space.tabulate_dof_coordinates()[:, :3].reshape(-1))
    u = fem.Function(space)
    u.interpolate(lambda x: np.stack([x[0] * x[1], np.sin(x[2]), x[0]]))
    u.x.scatter_forward()
    both = order.gather(np.stack([u.x.array, -u.x.array]))
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(pathlib.Path(builtin_model_path) / "mesh.h5") as h5:
            nodes = h5["Mesh/flesh/geometry"][:]
        assert gathered.shape == nodes.shape
        assert np.abs(gathered - nodes).max() < 1e-12
        assert np.array_equal(both[1], -both[0])
    both = MPI.COMM_WORLD.bcast(both, root=0)
    assert np.array_equal(order.scatter(both[0]), u.x.array)
    assert np.array_equal(order.scatter(both), np.stack([u.x.array, -u.x.array]))


def test_file_node_order_needs_p1(model):
    with pytest.raises(ValueError, match="P1"):
        FileNodeOrder(fem.VectorFunctionSpace(model.mesh, ("CG", 2)))




def test_xdmf_series_reads_back(tmp_path):
    meshio = pytest.importorskip("meshio")
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    cells = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    with XdmfSeries(tmp_path / "s.xdmf", points, cells) as series:
        for step in range(3):
            series.write(0.5 * step, {"displacement": step * points}, {"activation_m": np.array([step, 2.0 * step])})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.h5", "s.xdmf"]  # no temporary left
    reader = meshio.xdmf.TimeSeriesReader(tmp_path / "s.xdmf")
    read_points, read_cells = reader.read_points_cells()
    assert np.array_equal(read_points, points) and np.array_equal(read_cells[0].data, cells)
    time, point_data, cell_data = reader.read_data(2)
    assert time == 1.0
    assert np.array_equal(point_data["displacement"], 2 * points)
    assert np.array_equal(cell_data["activation_m"][0], [2.0, 4.0])


def test_xdmf_series_interrupted_leaves_nothing(tmp_path):
    with pytest.raises(ValueError, match="3 values for 2 cells"):
        with XdmfSeries(tmp_path / "s.xdmf", np.eye(4, 3), np.array([[0, 1, 2, 3], [0, 1, 2, 3]])) as series:
            series.write(0.0, {}, {"bad": np.zeros(3)})
    assert list(tmp_path.iterdir()) == []


def test_frame_ranges():
    assert frame_ranges([2, 3, 4, 5, 9]) == "2-5, 9"
    assert frame_ranges([0]) == "0"
