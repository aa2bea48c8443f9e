"""Offscreen skin renders (face_dolfinx.results.render): a picture with a face in it, and the rigid
objects touching it drawn where they stand. (Their speed is measured in benchmarks/, not asserted
here.)"""
import json

import matplotlib.image as mpimg
import matplotlib.pyplot as plt
import numpy as np
import pytest
from mpi4py import MPI

from face_dolfinx.model.folder import load_model
from face_dolfinx.physics.contact import Sphere
from face_dolfinx.results.render import OBJECT_COLOUR, draw_skin, render_skin
from test_contact import cheek_path


@pytest.fixture(scope="module")
def skin(builtin_model_path):
    model = load_model(builtin_model_path, MPI.COMM_WORLD)
    return model.skin_surface(), model.markers, model.landmarks


@pytest.mark.parametrize("view", ["front", "three_quarter", "side"])
def test_render_writes_a_shaded_picture(skin, tmp_path, view):
    (points, triangles), markers, landmarks = skin
    path = render_skin(points, triangles, tmp_path / f"{view}.png", markers=markers,
                       other_markers=landmarks, title=view, view=view)
    image = mpimg.imread(path)[:, :, :3]
    grey = image.mean(axis=2)
    covered = grey < 0.95                                  # not the white background
    assert 0.15 < covered.mean() < 0.95
    assert grey[covered].std() > 0.05                      # shaded, not a flat silhouette
    red = (image[:, :, 0] > 0.8) & (image[:, :, 1] < 0.3) & (image[:, :, 2] < 0.3)
    assert red.sum() > 20                                  # the markers are drawn


def test_render_scalars_per_point_and_per_triangle(skin, tmp_path):
    (points, triangles), _, _ = skin
    for name, values in (("points", points[:, 1]), ("triangles", np.arange(len(triangles), dtype=float))):
        image = mpimg.imread(render_skin(points, triangles, tmp_path / f"{name}.png", scalars=values))
        assert image[:, :, :3].std(axis=(0, 1)).max() > 0.05


def test_unknown_view(skin, tmp_path):
    (points, triangles), _, _ = skin
    with pytest.raises(ValueError, match="unknown view"):
        render_skin(points, triangles, tmp_path / "x.png", view="top")


def drawn_pixels(points, triangles, objects=()):
    """The front view as an RGB array, and a map from model (x, y) to (row, column) of it."""
    figure = draw_skin(points, triangles, view="front", objects=objects)
    figure.canvas.draw()
    image = np.asarray(figure.canvas.buffer_rgba())[:, :, :3].astype(float) / 255.0
    transform = figure.axes[0].transData
    height = image.shape[0]
    plt.close(figure)

    def pixel(xy):
        column, row = transform.transform(np.atleast_2d(xy)).T
        return height - row, column
    return image, pixel


def test_an_object_is_drawn_where_it_stands(skin, model):
    """A sphere just off the left cheek changes the picture inside its outline alone, in the
    objects' colour; one behind the face is hidden by it."""
    (points, triangles), _, _ = skin
    radius = 15.0
    sphere_points, sphere_triangles = Sphere(radius).surface()
    bare, pixel = drawn_pixels(points, triangles)
    centres = {"in front of the cheek": cheek_path(model, [-1.0], radius)[0],
               "behind the face": np.array([0.0, -20.0, points[:, 2].min() - 2.0 * radius])}
    changed = {}
    for where, centre in centres.items():
        image, _ = drawn_pixels(points, triangles, objects=[(sphere_points + centre, sphere_triangles)])
        assert image.shape == bare.shape
        changed[where] = np.abs(image - bare).max(axis=2) > 0.02
    rows, columns = np.indices(bare.shape[:2])
    row, column = pixel(centres["in front of the cheek"][:2])
    edge_row, edge_column = pixel(centres["in front of the cheek"][:2] + [radius, 0.0])
    disc_radius = np.hypot(edge_row - row, edge_column - column)[0]
    distance = np.hypot(rows - row[0], columns - column[0])
    in_front = changed["in front of the cheek"]
    assert in_front[distance < 0.9 * disc_radius].mean() > 0.95      # the sphere covers its disc ...
    assert not in_front[distance > 1.1 * disc_radius].any()           # ... and nothing else changes
    image, _ = drawn_pixels(points, triangles, objects=[(sphere_points + centres["in front of the cheek"],
                                                         sphere_triangles)])
    colour = image[distance < 0.5 * disc_radius].mean(axis=0)
    assert np.argmax(colour) == np.argmax(OBJECT_COLOUR) == 2        # blue, not the skin's tone
    assert changed["behind the face"].mean() < 1e-3


def test_simulate_renders_the_object(model, builtin_model_path, shared_dir):
    """run.py simulate --object with renders: a picture per pose of the object, the sphere drawn in
    the objects' colour where it stands (the render of the face without it has none)."""
    from face_dolfinx.cli.main import main
    path, out = shared_dir / "render_path.txt", shared_dir / "render_pressed"
    centres = cheek_path(model, [-1.0, 2.0])
    if MPI.COMM_WORLD.rank == 0:
        path.write_text("\n".join(" ".join(f"{v:.6f}" for v in c) for c in centres) + "\n")
    MPI.COMM_WORLD.barrier()
    assert main(["simulate", "smile", "--model", str(builtin_model_path), "--object", "sphere:15", "--path", str(path),
                 "--out", str(out)]) == 0
    assert [row["pose"] for row in json.loads((out / "summary.json").read_text())["object"]] == [0, 1]
    blue = {}
    for name in ("01_smile.png", "02_object.png"):
        image = mpimg.imread(out / name)[:, :, :3]
        blue[name] = int(((image[:, :, 2] > image[:, :, 0] + 0.1) & (image[:, :, 2] > 0.3)).sum())
    assert blue["01_smile.png"] > 2000 and blue["02_object.png"] > 2000
    bare = render_skin(*model.skin_surface(), shared_dir / f"bare{MPI.COMM_WORLD.rank}.png")
    image = mpimg.imread(bare)[:, :, :3]
    assert int(((image[:, :, 2] > image[:, :, 0] + 0.1) & (image[:, :, 2] > 0.3)).sum()) < 50
