"""Offscreen skin renders (face_dolfinx.results.render): a picture with a face in it. (Their speed
is measured in benchmarks/, not asserted here.)"""
import matplotlib.image as mpimg
import numpy as np
import pytest
from mpi4py import MPI

from face_dolfinx.model.folder import load_model
from face_dolfinx.results.render import render_skin


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
