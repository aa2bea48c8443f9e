"""Which controls the visible markers of a frame determine, from the marker Jacobian."""
import numpy as np

# An under-determined frame names the controls whose weight in the weak directions is at least
# this share of the largest: the ones that make up those directions, not every small contributor.
WEAK_SHARE = 0.5


def observability(marker_columns: np.ndarray, present: np.ndarray, threshold: float) -> tuple[float, np.ndarray]:
    """How well the visible markers determine the controls, from the marker Jacobian.

    ``marker_columns`` (controls, markers, 3): d(marker)/dc at every marker; ``present``: the
    visible markers. Each column is scaled by its norm over all markers, so that every control
    counts with the marker motion it causes in a complete frame. Combinations that move no marker
    even in a complete frame (a muscle no marker sees, redundant affine numbers) are the model's
    limit, not the frame's, and are left out. Returns

    - the smallest singular value of the scaled visible Jacobian over that of the scaled complete
      one: the least any combination of controls moves the visible markers, relative to the least
      a complete frame would show (1 with every marker present, 0 when some combination moves no
      visible marker);
    - per control, its weight in the weak directions, the right singular vectors of the scaled
      visible Jacobian whose singular value is below ``threshold`` times the complete frame's
      smallest: ||P_weak e_i||^2, 0 with no weak direction, 1 for a control lying in them.
    Both catch a control whose markers are missing and controls whose visible effects coincide.
    """
    count = len(marker_columns)
    response = np.linalg.norm(marker_columns.reshape(count, -1), axis=1)
    scale = np.where(response > 1e-12 * response.max(), response, np.inf)[:, None, None]
    scaled = marker_columns / scale
    _, values, directions = np.linalg.svd(scaled.reshape(count, -1).T, full_matrices=False)
    directions = directions[values > 1e-8 * values[0]]  # the combinations a complete frame sees
    floor = values[len(directions) - 1]
    visible = scaled[:, present].reshape(count, -1).T @ directions.T
    _, visible_values, visible_directions = np.linalg.svd(visible, full_matrices=True)
    visible_values = np.concatenate([visible_values,  # fewer visible rows than combinations
                                     np.zeros(len(directions) - len(visible_values))])
    weak = directions.T @ visible_directions[visible_values < threshold * floor].T
    return float(visible_values[-1] / floor), np.sum(weak**2, axis=1)
