"""Start a fine equilibrium solve from the equilibrium of a coarse model of the same face.

Nested iteration (grid sequencing): for a bone motion, Newton from rest on the fine mesh spends
most of its iterations, and its failed attempts, on the large nonlinear motion of the lower face
that a coarse mesh resolves as well; started from the coarse equilibrium interpolated onto its
nodes, the fine Newton only corrects the discretisation difference. (For muscle-driven shapes it
does not pay: see ``CoarseStart.solve``.) Measured on the built-in face, jaw opening by 15 degrees:
the 50K face took 19 Newton iterations in 2 load steps from rest, and 5 iterations in one step
from the 20K equilibrium (5.3 s for the coarse solve, 0.1 s for the transfer); at 404K tets on
2 ranks, 52 iterations in 3 load steps (226 s) against 9 in one from the 50K equilibrium (47 s
in all). docs/performance.md has the table.

The coarse mesh is small: every rank holds all of it (cells and rest coordinates) and locates its
fine nodes in it once. A fine node outside the coarse mesh (the two surfaces are facetted
differently) takes the linear extension of the nearest coarse cell's field.
"""
import logging
import time

from mpi4py import MPI
import numpy as np
from scipy.spatial import cKDTree

from .solver import SolveReport

log = logging.getLogger(__name__)

# Coarse cells (nearest by centroid) tried for each fine node: the host cell of an interior node
# was always among the 12 nearest on the built-in face from 5K to 400K tets.
CANDIDATE_CELLS = 12


class CoarseStart:
    """Solves ``coarse`` first and starts ``fine`` from its equilibrium.

    ``coarse`` must be a P1 ``FaceProblem`` of the same face (same muscles in the same order, same
    bone frames) on a coarser mesh; ``fine`` any ``FaceProblem``. ``max_outside`` bounds how far
    outside the coarse mesh a fine node may lie, in barycentric units of the nearest coarse cell
    (at most 0.34 between the built-in faces of 20K, 50K and 404K tets); farther means another
    face.
    """

    def __init__(self, coarse, fine, max_outside: float = 1.0):
        if coarse.V.ufl_element().degree() != 1:
            raise ValueError("the coarse problem must have P1 displacement")
        coarse_muscles = [m.name for m in coarse.model.muscles]
        fine_muscles = [m.name for m in fine.model.muscles]
        if coarse_muscles != fine_muscles:
            raise ValueError(f"coarse model {coarse.model.path} and fine model {fine.model.path} have "
                             f"different muscles: {sorted(set(coarse_muscles) ^ set(fine_muscles))} "
                             f"or another order")
        self.coarse, self.fine = coarse, fine
        self.comm = fine.comm
        index_map = coarse.V.dofmap.index_map
        self._owned = index_map.size_local
        self._global = index_map.local_to_global(
            np.arange(index_map.size_local + index_map.num_ghosts, dtype=np.int32))
        # Where each rank's owned coarse dofs go in the gathered array: fixed, so gathered once.
        self._gathered_ids = np.concatenate(self.comm.allgather(self._global[:self._owned]))
        rest = self._gather(coarse.dof_coordinates)
        num_cells = coarse.mesh.topology.index_map(3).size_local
        local_cells = self._global[coarse.V.dofmap.list.array.reshape(-1, 4)[:num_cells]]
        cells = np.concatenate(self.comm.allgather(local_cells))
        self._cells, self._weights, outside = locate_in_cells(rest, cells, fine.dof_coordinates)
        worst = self.comm.allreduce(outside.max(initial=0.0), op=MPI.MAX)
        if worst > max_outside:
            raise ValueError(
                f"fine model {fine.model.path}: a node lies {worst:.2f} cell sizes outside the coarse "
                f"model {coarse.model.path} (at most {max_outside} allowed): not the same face")

    def _gather(self, values: np.ndarray) -> np.ndarray:
        """The coarse dof values (rows = blocks) of all ranks, in global numbering, on every rank."""
        owned = values.reshape(-1, 3)[:self._owned]
        gathered = np.empty((self.coarse.V.dofmap.index_map.size_global, 3))
        gathered[self._gathered_ids] = np.concatenate(self.comm.allgather(owned))
        return gathered

    def guess(self) -> np.ndarray:
        """The coarse displacement at the fine dofs (local incl. ghosts, flat)."""
        coarse = self._gather(self.coarse.u.x.array)
        return np.einsum("ij,ijk->ik", self._weights, coarse[self._cells]).reshape(-1)

    def solve(self, activations=None, cranium=None, jaw=None) -> SolveReport:
        """Equilibrium of the fine problem for these controls (``FaceProblem.solve``'s meaning).
        When a bone frame moves, Newton starts from the coarse equilibrium (if it fails there, the
        fine problem's own continuation from its last equilibrium takes over) and the report is the
        fine solve's with the coarse solve's time included. Activations alone are solved on the fine
        model directly: started from the 50K equilibrium, the 404K smile and pucker failed their
        first Newton attempt (the guard cut 4 steps in a row) and fell back to continuation, 85 s
        and 71 s against 48-62 s and 70 s from their last equilibrium."""
        if not self._bones_move(cranium, jaw):
            return self.fine.solve(activations=activations, cranium=cranium, jaw=jaw)
        began = time.perf_counter()
        coarse = self.coarse.solve(activations=activations, cranium=cranium, jaw=jaw)
        # The bone nodes keep their interpolated values: Newton's first step puts them where the
        # bones are. Set there directly, they flattened the cells between them and the
        # interpolated flesh (404K from 50K, smile: the guard cut 8 steps, 16 iterations against 7).
        report = self.fine.solve(activations=activations, cranium=cranium, jaw=jaw, guess=self.guess())
        if self.comm.rank == 0:
            log.info("coarse start: coarse model %d Newton its in %d load steps, %.1f s; fine model "
                     "%d its, %.1f s", coarse.newton_iterations, coarse.load_steps, coarse.seconds,
                     report.newton_iterations, report.seconds)
        report.seconds = time.perf_counter() - began
        return report

    def _bones_move(self, cranium, jaw) -> bool:
        current = self.fine.controls
        return any(new is not None and not new.same_as(old)
                   for new, old in ((cranium, current.cranium), (jaw, current.jaw)))


def locate_in_cells(points: np.ndarray, cells: np.ndarray, targets: np.ndarray):
    """Host cell (as its 4 vertex ids) and barycentric weights of each target point in the
    tetrahedra ``cells`` over ``points``; a point in no cell gets the cell whose smallest
    barycentric coordinate is largest, with that cell's (extrapolating) weights. Also returns
    how far outside its cell each point lies (minus the smallest weight, 0 inside)."""
    corners = points[cells]
    _, nearest = cKDTree(corners.mean(axis=1)).query(targets, k=min(CANDIDATE_CELLS, len(cells)))
    nearest = nearest.reshape(len(targets), -1)
    best_score = np.full(len(targets), -np.inf)
    best_weights = np.zeros((len(targets), 4))
    best_cell = np.zeros(len(targets), dtype=np.int64)
    for candidate in nearest.T:
        P = corners[candidate]
        edges = np.transpose(P[:, 1:] - P[:, :1], (0, 2, 1))
        local = np.linalg.solve(edges, (targets - P[:, 0])[:, :, None])[:, :, 0]
        weights = np.column_stack([1.0 - local.sum(axis=1), local])
        score = weights.min(axis=1)
        better = score > best_score
        best_score[better], best_weights[better], best_cell[better] = score[better], weights[better], candidate[better]
    return cells[best_cell], best_weights, np.maximum(-best_score, 0.0)
