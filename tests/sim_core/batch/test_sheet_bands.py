"""The batched CG's band blocks of a stacked scene (sim_core.batch.sheet_bands): one block a copy's sheet, its
vertices along the sheet's long axis, which narrows the band of its bending stencil."""

from __future__ import annotations

import numpy as np

from sim_core.batch.sheet_bands import long_axis_order, sheet_band_dofs
from sim_core.batch.stacked import stack_models
from tests.support.batch_copies import pad_model


def _half_bandwidth(hinges: np.ndarray, position: np.ndarray) -> int:
    """The largest distance in ``position`` (vertex -> band position) between two vertices of one hinge."""
    p = position[hinges]
    return int((p.max(axis=1) - p.min(axis=1)).max())


def test_points_are_ordered_along_the_long_axis_of_a_turned_rectangle():
    ix, iy = np.meshgrid(np.arange(10), np.arange(3), indexing="ij")
    turn = np.array([[np.cos(0.6), -np.sin(0.6), 0.0], [np.sin(0.6), np.cos(0.6), 0.0], [0.0, 0.0, 1.0]])
    x = np.stack([ix.ravel() * 0.01, iy.ravel() * 0.01, np.zeros(30)], axis=1) @ turn.T
    shuffle = np.random.default_rng(0).permutation(30)
    order = long_axis_order(x[shuffle])
    along = ix.ravel()[shuffle][order]
    assert np.all(np.diff(along) >= 0)  # the rows across the short side follow each other


def test_each_copys_sheet_is_one_block_in_long_axis_order():
    model = pad_model()
    scene = stack_models([model, model, model])
    bands = sheet_band_dofs(scene)
    sheet = model.bodies["sheet"]
    m = 3 * (sheet.vertex_stop - sheet.vertex_start)
    assert bands.shape == (3, m)
    for c in range(3):
        stacked_sheet = scene.index[c][sheet.vertices]
        assert np.array_equal(np.sort(bands[c]), np.sort((3 * stacked_sheet[:, None] + np.arange(3)).ravel()))
        assert np.array_equal(bands[c].reshape(-1, 3) % 3, np.tile(np.arange(3), (m // 3, 1)))
    # the band order's hinges span no more positions than the vertex order's
    local = {int(v): k for k, v in enumerate(scene.index[0])}
    order = np.array([local[int(v)] for v in bands[0][::3] // 3])
    position = np.empty(model.vertex_count, dtype=np.int64)
    position[order] = np.arange(order.size)
    natural = np.arange(model.vertex_count)
    assert _half_bandwidth(sheet.hinges, position) <= _half_bandwidth(sheet.hinges, natural)


def test_the_sheets_fixed_vertices_are_left_out_of_its_block():
    model = pad_model()
    sheet = model.bodies["sheet"]
    held = sheet.vertices[[0, 1, 5]]
    model.vertex_fixed[held] = True
    scene = stack_models([model, model])
    bands = sheet_band_dofs(scene)
    free = np.setdiff1d(sheet.vertices, held)
    assert bands.shape == (2, 3 * free.size)
    for c in range(2):
        assert np.array_equal(np.sort(bands[c]), np.sort((3 * scene.index[c][free][:, None] + np.arange(3)).ravel()))
    model.vertex_fixed[sheet.vertices] = True  # a sheet fixed whole: no block
    assert sheet_band_dofs(stack_models([model, model])) is None


def test_a_scene_without_a_sheet_or_with_a_sheet_over_the_size_limit_has_no_blocks():
    model = pad_model()
    scene = stack_models([model, model])
    m = 3 * model.bodies["sheet"].vertices.size
    assert sheet_band_dofs(scene, max_dofs=m).shape == (2, m)
    assert sheet_band_dofs(scene, max_dofs=m - 1) is None
    for body in scene.model.bodies.values():
        if body.kind == "sheet":
            body.kind = "frozen"
    assert sheet_band_dofs(scene) is None
