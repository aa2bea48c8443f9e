"""A "user's own" marker set on a face model: every marker site and landmark, renamed as a user
might, with the correspondence file that names the landmark ones (shared by the CLI tests)."""
import numpy as np
from mpi4py import MPI


def user_sites(model):
    """Names ("M00", ...), points (n, 3) and correspondence {name: landmark} of the model's marker
    sites plus its landmarks; a landmark at a marker site (the built-in face puts the mouth corners
    and lip centres at both) is that marker."""
    sites = dict(model.markers)
    at_landmark = {}
    for landmark, point in model.landmarks.items():
        same = [name for name, site in sites.items() if np.linalg.norm(site - point) < 1e-9]
        at_landmark[landmark] = same[0] if same else f"landmark {landmark}"  # "nose_tip" names both
        sites.setdefault(at_landmark[landmark], point)
    user_name = {name: f"M{i:02d}" for i, name in enumerate(sites)}
    correspondence = {user_name[site]: landmark for landmark, site in at_landmark.items()}
    return list(user_name.values()), np.array(list(sites.values())), correspondence


def write_correspondence(path, correspondence):
    """A [correspondence] TOML file, written by rank 0 and seen by all ranks."""
    if MPI.COMM_WORLD.rank == 0:
        path.write_text("[correspondence]\n" + "".join(f'{m} = "{lm}"\n' for m, lm in correspondence.items()))
    MPI.COMM_WORLD.barrier()
    return path
