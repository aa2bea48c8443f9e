"""Results on disk: XDMF (ParaView) of the deformed face, point evaluation.

Fields that must not depend on how the mesh was distributed (a fit's per-frame displacement and
its resume checkpoint) are stored in the mesh file's node order (``FileNodeOrder``); ``XdmfSeries``
writes a ParaView time series from such arrays on one process, with the mesh as the file gives it.
"""
import pathlib

from mpi4py import MPI
import h5py
import numpy as np
from dolfinx import fem, io

from face_dolfinx.files import AtomicFile, atomic_write
from face_dolfinx.physics.points import PointEvaluator


def displacement_at(u: fem.Function, points: np.ndarray) -> np.ndarray:
    """u at ``points`` (n, 3) of the reference configuration, the same array on every rank."""
    return PointEvaluator(u.function_space, points).values(u.x.array)


class FaceWriter:
    """XDMF time series of the face: displacement, each muscle's activation x fraction, fibers."""

    def __init__(self, problem, path):
        self.problem = problem
        mesh = problem.mesh
        self._file = io.XDMFFile(mesh.comm, str(path), "w")
        self._file.write_mesh(mesh)
        self._P1 = fem.VectorFunctionSpace(mesh, ("CG", 1))
        self._displacement = fem.Function(self._P1, name="displacement")
        DG0 = fem.FunctionSpace(mesh, ("DG", 0))
        self._muscle_fields = [fem.Function(DG0, name=f"activation_{m.name}") for m in problem.model.muscles]
        self._fiber = fem.Function(fem.VectorFunctionSpace(mesh, ("DG", 0)), name="fiber")
        # The fiber shown per cell is that of its strongest muscle (slot weights are fixed).
        slots = problem.slots
        weights = np.stack([w.x.array for w in slots.weight])
        strongest = np.argmax(weights, axis=0)
        fibers = np.stack([f.x.array.reshape(-1, 3) for f in slots.fiber])
        self._fiber.x.array[:] = fibers[strongest, np.arange(len(strongest))].reshape(-1)
        self._fiber.x.array.reshape(-1, 3)[weights.max(axis=0) == 0] = 0.0
        self._file.write_function(self._fiber, 0.0)

    def write(self, time: float) -> None:
        problem = self.problem
        self._displacement.interpolate(problem.u)
        self._file.write_function(self._displacement, time)
        slots = problem.slots
        for index, field in enumerate(self._muscle_fields):
            field.x.array[:] = 0.0
            for k in range(len(slots.weight)):
                in_slot = slots.muscle_of_slot[k] == index
                stress = slots.weight[k].x.array / max(problem.peak_stress(index), 1e-300)
                field.x.array[in_slot] = problem.controls.activations[index] * stress[in_slot]
            self._file.write_function(field, time)

    def close(self) -> None:
        self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class FileNodeOrder:
    """Dof blocks of a P1 space on this rank <-> the node numbering of the mesh file.

    A P1 dof block sits on one mesh node, and DOLFINx keeps each node's index in the file
    (``geometry.input_global_indices``), so a field gathered in file order is the same however
    many ranks computed it, and can be put back on any distribution of the mesh.
    """

    def __init__(self, space: fem.FunctionSpace):
        mesh = space.mesh
        if space.ufl_element().degree() != 1 or mesh.ufl_domain().ufl_coordinate_element().degree() != 1:
            raise ValueError("FileNodeOrder needs a P1 space on a linear mesh")
        self.comm = mesh.comm
        index_map = space.dofmap.index_map
        self.block_size = space.dofmap.index_map_bs
        self.owned = index_map.size_local
        # Dofs and geometry nodes of a cell follow the same reference vertex order.
        dofs = space.dofmap.list.array.reshape(-1, 4)
        nodes = mesh.geometry.dofmap.array.reshape(-1, 4)
        self.file_node = np.empty(index_map.size_local + index_map.num_ghosts, dtype=np.int64)
        self.file_node[dofs] = np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)[nodes]
        self.num_nodes = self.comm.allreduce(int(self.file_node.max(initial=-1)) + 1, op=MPI.MAX)

    def gather(self, arrays: np.ndarray) -> np.ndarray | None:
        """Local dof arrays (..., local dofs incl. ghosts) -> (..., file nodes, block size) on
        rank 0 (None elsewhere). Collective. Nodes no cell uses read 0."""
        arrays = np.asarray(arrays)
        leading = arrays.shape[:-1]
        blocks = arrays.reshape(*leading, -1, self.block_size)[..., :self.owned, :]
        pieces = self.comm.gather((self.file_node[:self.owned], blocks), root=0)
        if self.comm.rank != 0:
            return None
        result = np.zeros((*leading, self.num_nodes, self.block_size))
        for file_node, values in pieces:
            result[..., file_node, :] = values
        return result

    def scatter(self, arrays: np.ndarray) -> np.ndarray:
        """The inverse of ``gather`` on every rank: (..., file nodes, block size) -> local dof
        arrays (..., local dofs incl. ghosts)."""
        arrays = np.asarray(arrays)
        local = arrays[..., self.file_node, :]
        return local.reshape(*arrays.shape[:-2], -1)


class XdmfSeries:
    """An XDMF time series (ParaView) of a tetrahedral mesh with node and cell fields, written by
    one process from plain arrays. ``path.with_suffix(".h5")`` holds the data. Both files appear
    only when ``close`` succeeds, so an interrupted write leaves no half-written series."""

    def __init__(self, path, points: np.ndarray, cells: np.ndarray):
        self.path = pathlib.Path(path)
        self.heavy = self.path.with_suffix(".h5")
        self._staged_heavy = AtomicFile(self.heavy)
        self._h5 = h5py.File(self._staged_heavy.temporary, "w")
        self._write("mesh/geometry", np.asarray(points, dtype=float))
        self._write("mesh/topology", np.asarray(cells, dtype=np.int64))
        self._num_points, self._num_cells = len(points), len(cells)
        self._grids = []

    def _write(self, name: str, values: np.ndarray) -> str:
        # Compressed: muscle fields are zero outside their muscle. No timestamps, so the same
        # data give the same file.
        self._h5.create_dataset(name, data=values, compression="gzip", shuffle=True, track_times=False)
        return f"{self.heavy.name}:/{name}"

    def write(self, time: float, point_fields: dict, cell_fields: dict) -> None:
        """One time step: {name: (points, 3) or (points,)} and {name: (cells,)} arrays."""
        step = len(self._grids)
        attributes = []
        for center, fields, count in (("Node", point_fields, self._num_points),
                                      ("Cell", cell_fields, self._num_cells)):
            for name, values in fields.items():
                values = np.asarray(values, dtype=float)
                if len(values) != count:
                    raise ValueError(f"field {name!r} has {len(values)} values for {count} {center.lower()}s")
                kind = "Vector" if values.ndim == 2 else "Scalar"
                dimensions = " ".join(str(n) for n in values.shape)
                location = self._write(f"step_{step:06d}/{name}", values)
                attributes.append(
                    f'        <Attribute Name="{name}" AttributeType="{kind}" Center="{center}">\n'
                    f'          <DataItem Dimensions="{dimensions}" Format="HDF">{location}</DataItem>\n'
                    f'        </Attribute>')
        self._grids.append(
            f'      <Grid Name="step_{step:06d}" GridType="Uniform">\n'
            f'        <xi:include xpointer="xpointer(/Xdmf/Domain/Grid[@Name=\'mesh\']/*[self::Topology or self::Geometry])" />\n'
            f'        <Time Value="{time!r}" />\n' + "\n".join(attributes) + "\n      </Grid>")

    def close(self) -> None:
        self._h5.close()
        self._staged_heavy.commit()
        text = f"""<?xml version="1.0"?>
<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>
<Xdmf Version="3.0" xmlns:xi="http://www.w3.org/2001/XInclude">
  <Domain>
    <Grid Name="mesh" GridType="Uniform">
      <Topology TopologyType="Tetrahedron" NumberOfElements="{self._num_cells}" NodesPerElement="4">
        <DataItem Dimensions="{self._num_cells} 4" NumberType="Int" Format="HDF">{self.heavy.name}:/mesh/topology</DataItem>
      </Topology>
      <Geometry GeometryType="XYZ">
        <DataItem Dimensions="{self._num_points} 3" Format="HDF">{self.heavy.name}:/mesh/geometry</DataItem>
      </Geometry>
    </Grid>
    <Grid Name="series" GridType="Collection" CollectionType="Temporal">
""" + "\n".join(self._grids) + """
    </Grid>
  </Domain>
</Xdmf>
"""
        atomic_write(self.path, text)

    def abort(self) -> None:
        self._h5.close()
        self._staged_heavy.discard()

    def __enter__(self):
        return self

    def __exit__(self, kind, *exc):
        self.close() if kind is None else self.abort()
