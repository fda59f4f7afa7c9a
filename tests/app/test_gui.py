"""The GUI without a browser: setting a handle's value runs its callback (viser calls update
callbacks synchronously for values set from Python); assert on the state and the scene handles.

References come from the core called directly on the same cloud (``decompose``, the pool), not
from the app."""

from __future__ import annotations

import dataclasses
import html
import re
import time
from types import SimpleNamespace

import numpy as np
import pytest

from app.scene import NAMES
from app.scene_data import ghost_selection, node_color
from app.state import ALL
from pregrasp_core.decomposition import decompose


def shown_text(markdown: str) -> str:
    """The text a markdown source shows (backslash escapes and entities resolved)."""
    return html.unescape(re.sub(r"\\(.)", r"\1", markdown))


def _box_handles(app) -> dict[int, object]:
    """Box handles found in viser's scene by their fixed names (what the scene really holds)."""
    out = {}
    for i in range(len(app.controller.state.tree.nodes)):
        h = app.server.scene.get_handle_by_name(f"{NAMES['boxes']}/node_{i}")
        if h is not None:
            out[i] = h
    return out


def _boxes_label(app) -> int:
    text = app.gui.boxes.content
    assert text.startswith("boxes: "), text
    return int(text.split()[1])


def test_start_shows_the_leaves_of_the_default_object(app):
    s = app.controller.state
    assert s.source.name == "mug_handle"
    assert len(s.cloud.points) == 3000
    leaves = s.tree.leaves()
    handles = _box_handles(app)
    assert sorted(handles) == sorted(leaves) == app.scene.box_ids
    assert _boxes_label(app) == len(leaves)
    for i, h in handles.items():  # each box sits where the core put it, with its size
        box = s.tree.node(i).box
        np.testing.assert_allclose(h.position, box.center, atol=1e-6)
        np.testing.assert_allclose(sorted(h.dimensions), sorted(box.extents), rtol=1e-5)
    cloud = app.server.scene.get_handle_by_name(NAMES["cloud"])
    assert cloud.points.dtype == np.float32 and cloud.points.shape == (3000, 3)
    np.testing.assert_allclose(cloud.points, s.cloud.points, atol=1e-6)


def test_threshold_change_reruns_decomposition_and_updates_scene(app):
    s0 = app.controller.state
    n0 = len(s0.tree.leaves())
    # the reference: the core's own decomposition of the same cloud with the new thresholds
    candidates = [(0.5, 500), (0.97, 100), (0.99, 50)]
    for ratio, min_pts in candidates:
        params = dataclasses.replace(
            s0.params.decomposition, volume_ratio=ratio, min_points=min_pts
        )
        expected = decompose(s0.cloud.points, params)
        if len(expected.leaves()) != n0:
            break
    else:
        pytest.fail("no candidate threshold changes the number of parts of the mug")
    app.gui.params[("decomposition", "min_points")].value = min_pts
    app.gui.params[("decomposition", "volume_ratio")].value = ratio
    s = app.controller.state
    assert s.params.decomposition.volume_ratio == ratio
    assert s.params.decomposition.min_points == min_pts
    assert len(s.tree.leaves()) == len(expected.leaves()) != n0
    assert _boxes_label(app) == len(expected.leaves()) == len(_box_handles(app))
    got = sorted(tuple(np.round(s.tree.node(i).box.center, 6)) for i in s.tree.leaves())
    want = sorted(tuple(np.round(expected.node(i).box.center, 6)) for i in expected.leaves())
    assert got == want
    assert s.error == ""


def test_level_slider_steps_through_the_splits(app):
    s = app.controller.state
    n = s.tree.n_splits
    assert app.gui.level.max == max(n, 1) and app.gui.level.value == n
    app.gui.level.value = 0
    assert app.controller.state.shown_level == 0
    assert sorted(_box_handles(app)) == [0] and _boxes_label(app) == 1
    colors = app.server.scene.get_handle_by_name(NAMES["cloud"]).colors
    assert np.all(colors == np.array(node_color(0)))  # one box: one colour
    app.gui.level.value = n
    assert sorted(_box_handles(app)) == sorted(s.tree.leaves())
    colors = app.server.scene.get_handle_by_name(NAMES["cloud"]).colors
    for i in s.tree.leaves():  # points coloured by the leaf that holds them
        assert np.all(colors[s.tree.node(i).indices] == np.array(node_color(i)))


def test_click_on_box_selects_node_and_shows_its_card(app):
    s = app.controller.state
    leaf = s.tree.leaves()[-1]
    box = app.server.scene.get_handle_by_name(f"{NAMES['boxes']}/node_{leaf}")
    for entry in box._impl.click_cb:  # what viser runs when a browser clicks that box
        entry.callback(SimpleNamespace(client=None, target=box, event="click"))
    s = app.controller.state
    assert s.view.selected_node == leaf
    text = shown_text(app.gui.node_info.content)
    shape = s.result.shapes[leaf]
    assert f"node {leaf}" in text
    assert f"class: {shape.shape_class.value}" in text
    assert f"grasp type: {shape.grasp_type.value}" in text
    assert f"points: {len(s.tree.node(leaf).indices)}" in text
    rows = [ln for ln in text.splitlines() if ln.startswith("| ") and ln[2].isdigit()]
    assert len(rows) == 6
    cells = [r.strip("| ").split(" | ") for r in rows]
    mask = np.array([[int(x) for x in c[1:6]] for c in cells])
    np.testing.assert_array_equal(mask, s.result.masks.mask(leaf))
    for f, c in enumerate(cells):  # "blocked by" names the core's blockers of each face
        by = c[6] if len(c) > 6 else ""
        want = [f"node {b}" for b in s.result.masks.blockers[leaf][f]]
        want += ["table"] if s.result.masks.by_support[leaf][f] else []
        assert by == ", ".join(want)
        assert bool(by) == bool(mask[f, 0])  # blocked exactly when something blocks it
    assert app.server.scene.get_handle_by_name(f"{NAMES['boxes']}/node_{leaf}").opacity == 0.35


def test_face_masks_drawn_free_and_blocked(app):
    s = app.controller.state
    shown = s.shown_nodes()
    blocked = int(sum(s.result.masks.blocked[i].sum() for i in shown))
    assert app.scene.n_faces_shown == (6 * len(shown) - blocked, blocked)
    if blocked:
        h = app.server.scene.get_handle_by_name(NAMES["faces_blocked"])
        assert h.batched_positions.shape == (blocked, 3)
    app.gui.show_masks.value = False
    assert app.scene.n_faces_shown == (0, 0)
    assert app.server.scene.get_handle_by_name(NAMES["faces_free"]) is None


def _assert_ghosts_at_pool_poses(app, pool, passing: np.ndarray) -> None:
    """Each drawn ghost is a distinct pre-grasp passing the filters, outlined where the pool
    puts it: its first 12 segments are the edges of the hand's palm box moved by the
    pre-grasp's ``T_world_hand`` (position and orientation), and its finger chains end at the
    fingertips of the hand's kinematics at the pre-grasp's joints (finger directions)."""
    hand = app.scene.hand
    idx = np.asarray(app.scene.ghost_indices)
    assert len(idx) == app.scene.n_ghosts_shown == len(set(idx.tolist()))
    assert passing[idx].all()
    pts = np.concatenate([h.points for h in app.scene.ghost_handles()]).astype(np.float64)
    S = 12 + len(hand.link_names) - 1
    assert pts.shape == (len(idx) * S, 2, 3)
    palm = hand.palm_box.corners()  # (8, 3) hand frame
    T_all = np.asarray(pool.T_world_hand)
    for k, i in enumerate(idx.tolist()):
        seg = pts[k * S : (k + 1) * S]
        T = T_all[i]
        want = palm @ T[:3, :3].T + T[:3, 3]
        got = np.unique(np.round(seg[:12].reshape(-1, 3), 6), axis=0)
        np.testing.assert_allclose(got, np.unique(np.round(want, 6), axis=0), atol=2e-6)
        tips = [T[:3, :3] @ p + T[:3, 3] for p in hand.fingertips(np.asarray(pool.q)[i]).values()]
        ends = seg[12:, 1]  # the chains' far ends (3 links per finger, in link order)
        for tip in tips:
            assert np.min(np.linalg.norm(ends - tip, axis=1)) < 1e-5
    colors = np.concatenate([h.colors for h in app.scene.ghost_handles()])
    assert len(colors) == len(pts)


def test_ghost_filters(app):
    s = app.controller.state
    pool = s.result.pool
    assert len(pool) > 0
    assert not s.view.show_ghosts and app.scene.n_ghosts_shown == 0  # off on the first screen
    assert app.scene.max_ghosts == 24  # few when shown: light enough for software WebGL
    app.gui.show_ghosts.value = True
    assert app.scene.n_ghosts_shown == min(len(pool), app.scene.max_ghosts)
    _assert_ghosts_at_pool_poses(app, pool, ghost_selection(pool, ALL, None))
    types = sorted(set(np.asarray(pool.grasp_type).tolist()))
    gt = types[0]
    app.gui.ghost_type.value = gt
    want = int(ghost_selection(pool, gt, None).sum())
    assert want == int((np.asarray(pool.grasp_type) == gt).sum())
    assert app.scene.n_ghosts_shown == min(want, app.scene.max_ghosts)
    _assert_ghosts_at_pool_poses(app, pool, np.asarray(pool.grasp_type) == gt)
    node = int(np.asarray(pool.node)[0])
    app.gui.ghost_type.value = ALL
    app.gui.ghost_node.value = f"node {node}"
    assert app.controller.state.view.ghost_node == node
    want = int((np.asarray(pool.node) == node).sum())
    assert app.scene.n_ghosts_shown == min(want, app.scene.max_ghosts)
    app.gui.show_ghosts.value = False
    assert app.scene.n_ghosts_shown == 0


def test_bad_threshold_is_reported_and_reverted(app):
    s0 = app.controller.state
    h = app.gui.params[("decomposition", "volume_ratio")]
    h.value = 1.5  # outside (0, 1]: DecompositionParams refuses it
    s = app.controller.state
    assert "volume_ratio" in s.error
    assert s.params == s0.params and s.result is s0.result
    assert h.value == s0.params.decomposition.volume_ratio  # the input shows the state again
    app.gui.level.value = 0  # the app still works
    assert app.controller.state.shown_level == 0


class _Browser:
    """Stands in for a browser: edits from a browser carry their client."""

    def add_notification(self, *a, **k):
        raise AssertionError(f"unexpected notification {a}")


def _browser_edit(handle, value) -> None:
    """What viser does with a browser's edit: store the value, then run the callbacks (viser
    runs them on its thread pool; here on the calling thread)."""
    from viser._gui_handles import GuiEvent

    handle._impl.value = value
    for cb in handle._impl.update_cb:
        cb(GuiEvent(client=_Browser(), client_id=1, target=handle))


def _count_runs(monkeypatch, hold: str | None = None):
    """Record every ``run_pipeline`` call (until, params); with ``hold``, the first call of
    that kind waits for ``gate`` (returned with the list and the event ``held`` it sets)."""
    import threading

    from pregrasp_core import pipeline as ppl

    real, calls = ppl.run_pipeline, []
    gate, held = threading.Event(), threading.Event()

    def run(cloud, params, hand=None, until="pool", **kw):
        calls.append((until, params))
        if until == hold and not held.is_set():
            held.set()
            assert gate.wait(60), "the test never released the held run"
        return real(cloud, params, hand, until=until, **kw)

    monkeypatch.setattr(ppl, "run_pipeline", run)
    return calls, gate, held


def _settle(app, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    c = app.controller
    while not (app.gui.settled() and c.idle() and c.state.busy == ""):
        assert time.monotonic() < deadline, "the edits never settled"
        time.sleep(0.01)


def test_a_browser_edit_of_a_threshold_applies_at_once(app, monkeypatch):
    """No wait for the control to rest: the edit's callback runs the pipeline itself, once."""
    calls, _, _ = _count_runs(monkeypatch)
    h = app.gui.params[("decomposition", "min_points")]
    want = app.controller.state.params.decomposition.min_points // 2
    _browser_edit(h, want)  # returns when the new scene is committed
    s = app.controller.state
    assert s.params.decomposition.min_points == want and s.error == ""
    assert s.result.params.decomposition.min_points == want
    assert [until for until, _ in calls] == ["pool"]
    _settle(app)  # the value in use is sent to the browsers once the control rests
    assert h.value == want and [until for until, _ in calls] == ["pool"]
    want_leaves = decompose(s.cloud.points, s.params.decomposition).leaves()
    assert sorted(s.tree.leaves()) == sorted(want_leaves) == app.scene.box_ids


def test_a_burst_of_browser_edits_ends_with_the_last_value_and_runs_the_pipeline_twice(
    app, monkeypatch
):
    """Typing 600 sends 6, 60 and 600: 6 runs at once; 60 and 600 arrive while it runs and are
    coalesced (the latest wins) and 6, now stale, is cancelled; 600 runs when it ends."""
    import threading

    calls, gate, held = _count_runs(monkeypatch, hold="pool")
    committed = []
    app.controller.subscribe(lambda s: committed.append(s.params.decomposition.min_points))
    h = app.gui.params[("decomposition", "min_points")]
    first = threading.Thread(target=_browser_edit, args=(h, 6))
    first.start()  # viser runs each edit's callback on its own pool thread
    assert held.wait(30), "the first edit did not start at once"
    for typed in (60, 600):  # arrive while 6 runs: their callbacks return at once
        t0 = time.monotonic()
        _browser_edit(h, typed)
        assert time.monotonic() - t0 < 1.0
    assert not app.gui.settled()
    gate.set()
    first.join(timeout=120)
    _settle(app)
    s = app.controller.state
    assert s.params.decomposition.min_points == 600 == s.result.params.decomposition.min_points
    assert s.error == "" and h.value == 600
    runs = [p.decomposition.min_points for _, p in calls]
    assert runs == [6, 600], runs  # the pipeline ran twice: never for 60
    assert 60 not in committed and 6 not in committed  # 6 was cancelled before its commit
    want_leaves = decompose(s.cloud.points, s.params.decomposition).leaves()
    assert sorted(s.tree.leaves()) == sorted(want_leaves) == app.scene.box_ids


def test_view_edits_arriving_while_one_runs_merge_into_the_last(app, monkeypatch):
    """The level slider: 0 runs and is held; 1, 0, 1 ... (50 edits) arrive meanwhile and return
    at once; when 0 ends, only the last of them runs. The level shown is the last edit's, in
    the state and the widget."""
    import threading

    c = app.controller
    n = c.state.tree.n_splits
    assert n >= 1
    real, levels = c.set_level, []
    gate, held = threading.Event(), threading.Event()

    def set_level(level):
        levels.append(level)
        if not held.is_set():
            held.set()
            assert gate.wait(60), "the test never released the held edit"
        return real(level)

    monkeypatch.setattr(c, "set_level", set_level)
    h = app.gui.level
    first = threading.Thread(target=_browser_edit, args=(h, 0))
    first.start()
    assert held.wait(30), "the first edit did not start at once"
    for i in range(50):
        t0 = time.monotonic()
        _browser_edit(h, (i + 1) % 2)
        assert time.monotonic() - t0 < 1.0  # merged: its callback returned without running
    gate.set()
    first.join(timeout=60)
    _settle(app)
    assert levels == [0, 0], levels  # the 50th edit sent 0: it ran, the other 49 never did
    s = c.state
    assert s.view.level == 0 and s.error == ""
    assert h.value == 0


def test_a_refused_edit_after_a_cancelled_one_leaves_the_earlier_edit_applied(app, monkeypatch):
    """60 runs and is cancelled by a newer edit, 2, which the parameters refuse (min points
    >= 4; a browser past the guard): the refusal is shown and 60, whose run was cancelled, is
    computed after all (``Controller.run_pending``), not lost."""
    import threading

    from viser._gui_handles import GuiEvent

    notices = []

    class Browser:
        def add_notification(self, title, body, **kw):
            notices.append(f"{title}: {body}")

    calls, gate, held = _count_runs(monkeypatch, hold="pool")
    h = app.gui.params[("decomposition", "min_points")]
    first = threading.Thread(target=_browser_edit, args=(h, 60))
    first.start()
    assert held.wait(30)
    h._impl.value = 2
    for cb in h._impl.update_cb:
        cb(GuiEvent(client=Browser(), client_id=2, target=h))
    gate.set()
    first.join(timeout=120)
    _settle(app)
    s = app.controller.state
    assert any("min_points" in n for n in notices), notices
    assert s.params.decomposition.min_points == 60 == s.result.params.decomposition.min_points
    assert [p.decomposition.min_points for _, p in calls] == [60, 60]  # cancelled, run again
    assert h.value == 60


def test_an_edit_during_the_replan_cancels_it_and_the_grasps_follow_the_last_edit(app, monkeypatch):
    """After planning, a threshold edit shows its scene and re-plans; a second edit arriving
    during that re-plan cancels it (stale) and runs when it ends: scene, then a re-plan for the
    second value. No grasps of the first value are ever committed."""
    import threading

    c = app.controller
    c.plan()
    assert c.state.planned
    calls, gate, held = _count_runs(monkeypatch, hold="grasps")
    planned = []
    c.subscribe(lambda s: planned.append(s.params.decomposition.volume_ratio) if s.planned else 0)
    h = app.gui.params[("decomposition", "volume_ratio")]
    first = threading.Thread(target=_browser_edit, args=(h, 0.5))
    first.start()
    assert held.wait(60), "the re-plan of the first edit never started"
    # the re-plan starts before the new scene is committed (Controller._rerun): wait for it
    deadline = time.monotonic() + 60
    while c.state.params.decomposition.volume_ratio != 0.5:
        assert time.monotonic() < deadline, "the scene of the first edit was never committed"
        time.sleep(0.005)
    assert c.state.busy == "plan" and c.state.replanning
    _browser_edit(h, 0.9)  # waits for the re-plan of 0.5 to stop
    gate.set()
    first.join(timeout=120)
    _settle(app)
    s = c.state
    assert s.planned and s.error == "" and not s.replanning
    assert s.params.decomposition.volume_ratio == 0.9
    assert s.result.params.decomposition.volume_ratio == 0.9 and s.result.grasps is not None
    assert set(planned) == {0.9}, planned  # the grasps shown are those of the last edit
    kinds = [(until, p.decomposition.volume_ratio) for until, p in calls]
    assert kinds == [("pool", 0.5), ("grasps", 0.5), ("pool", 0.9), ("grasps", 0.9)], kinds
    assert h.value == 0.9


def test_progress_reports_move_the_bar_and_other_changes_the_whole_panel(app):
    """A plan's progress report (a state that differs only by its progress) moves the progress
    bar alone; any other change is mirrored as a whole (here the status line)."""
    from app.gui import changed_fields

    c = app.controller
    s0 = c.state
    assert changed_fields(s0, dataclasses.replace(s0, progress=0.5, version=9)) == {"progress"}
    assert changed_fields(s0, dataclasses.replace(s0, message="x")) == {"message"}
    c.update(lambda s: dataclasses.replace(s, busy="plan", progress=0.0))
    assert app.gui.progress.visible and app.gui.plan.label == "planning..."
    for p in (0.25, 0.5, 0.75):
        c.update(lambda s, p=p: dataclasses.replace(s, progress=p))
        assert app.gui.progress.value == 100.0 * p
    c.update(lambda s: dataclasses.replace(s, busy="", progress=0.0, message="all done"))
    assert not app.gui.progress.visible and app.gui.plan.label == "plan grasps"
    assert shown_text(app.gui.status.content) == "all done"


def test_the_animation_clock_moves_the_phase_slider(app):
    """A tick of the animation clock (only the view's phase changes) moves the phase slider;
    the hand is posed by the scene for that phase; any other view change still updates the
    panel as a whole."""
    c = app.controller
    c.plan()
    c.select_grasp(0)
    for t in (0.1, 0.37, 0.8):
        c.update(lambda s, t=t: dataclasses.replace(s, view=dataclasses.replace(s.view, anim_t=t)))
        assert app.gui.phase.value == round(t, 2)
        assert app.scene.rendered is c.state
    c.tick(10.0)  # to the closed hand: the clock stops
    assert app.gui.phase.value == 1.0 and not c.state.view.playing
    gt = app.gui.ghost_type.options[1]
    app.gui.ghost_type.value = gt  # another view change: the panel as a whole
    pool = c.state.result.pool
    want = int(ghost_selection(pool, gt, None).sum())
    assert c.state.view.ghost_type == gt and f"{want} pass the filters" in app.gui.pool_info.content


def test_concurrent_callbacks_leave_scene_and_state_consistent(app):
    """viser runs callbacks on a thread pool: actions from several browsers at once must not
    interleave (the controller's lock), so the scene always matches the final state."""
    import threading

    n = app.controller.state.tree.n_splits
    errors = []

    def worker(k: int) -> None:
        try:
            for j in range(4):
                if k % 2:
                    app.controller.set_param("decomposition", "volume_ratio", (0.5, 0.9)[j % 2])
                else:
                    app.controller.set_level((0, n)[j % 2] if j % 2 == 0 else None)
                    app.controller.select_node(0)
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not errors, errors
    s = app.controller.state
    assert sorted(_box_handles(app)) == sorted(s.shown_nodes()) == app.scene.box_ids
    assert _boxes_label(app) == len(s.shown_nodes())
    colors = app.server.scene.get_handle_by_name(NAMES["cloud"]).colors
    for i in s.shown_nodes():
        assert np.all(colors[s.tree.node(i).indices] == np.array(node_color(i)))


def test_every_level_shows_the_cut_of_the_tree(app):
    """Each slider position shows exactly the core's cut after that many splits."""
    app.gui.params[("decomposition", "min_points")].value = 100  # more parts: more levels
    s = app.controller.state
    n = s.tree.n_splits
    assert n >= 2, "the mug at 100 points per part should split at least twice"
    for k in range(n + 1):
        app.gui.level.value = k
        want = sorted(s.tree.cut_at_level(k))
        assert sorted(_box_handles(app)) == want == app.scene.box_ids
        assert _boxes_label(app) == len(want)
        labels = s.tree.point_labels(want)
        colors = app.server.scene.get_handle_by_name(NAMES["cloud"]).colors
        for i in want:
            assert np.all(colors[labels == i] == np.array(node_color(i)))


def test_legend_names_every_colour_of_the_scene(app):
    from app.scene_data import GHOST_RGB

    text = shown_text(app.gui.legend.content)
    for word in ("free faces", "blocked faces", "usable sub-faces", "contacts", "friction cones"):
        assert word in text
    for gt in GHOST_RGB:  # one row per grasp type of the ghosts
        assert gt.replace("_", "-") + " pre-grasps" in text
    assert "epsilon" in text and "not force closure" in text


def test_the_grasp_table_counts_the_contacts_at_edges_of_a_cloud_without_normals(
    make_app, tmp_path
):
    """A PLY with xyz only: the contacts whose normal is the mean of the cloud's and the
    link's (at crest points, ``Contact.crest``) are counted in the grasp table's contacts
    column, per grasp; a mesh (with normals) has none."""
    from app.gui import grasp_table
    from pregrasp_core.io import load_point_cloud
    from pregrasp_core.paths import DEFAULT_OBJECT
    from tests.app.conftest import APP_POINTS

    pts = np.asarray(load_point_cloud(DEFAULT_OBJECT, n_points=APP_POINTS, seed=0).points)
    path = tmp_path / "bare.ply"
    header = f"ply\nformat ascii 1.0\nelement vertex {len(pts)}\n"
    header += "property float x\nproperty float y\nproperty float z\nend_header\n"
    path.write_text(header + "\n".join(f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in pts) + "\n")
    app = make_app(input=path)
    s = app.controller.plan()
    assert s.error == "" and s.result.grasps is not None and s.result.crest is not None
    table = grasp_table(s)
    counts = [sum(c.crest for c in g.contacts) for g in s.result.grasps.ranked]
    assert any(counts)
    rows = [r for r in table.splitlines() if r.startswith("| ") and r[2].isdigit()]
    assert rows and any("at edges" in r for r in rows)
    for r in rows:  # the shown rows: ranked grasps, best first
        k = int(r.split("|")[1]) - 1
        assert (f"{counts[k]} at edges" in r) == bool(counts[k]), r
    assert "at edges" not in grasp_table(make_app().controller.plan())


def test_the_up_dropdown_plans_a_y_up_mesh_standing_and_turns_the_view(make_app, tmp_path):
    """The default object turned to stand along +y (as glTF, Blender's and ShapeNet's files
    are) opens lying on its side (up +z: its support plane is its side); 'up' +y plans it
    standing: the pool is the core's with ``FaceMaskParams(up=(0, 1, 0))`` on the same cloud,
    the table grid lies in the plane y = its lowest y, the scene's up is +y and the camera
    looks from above along it."""
    import trimesh
    from scipy.spatial.transform import Rotation

    from pregrasp_core.facemask import FaceMaskParams
    from pregrasp_core.paths import DEFAULT_OBJECT
    from pregrasp_core.pipeline import run_pipeline

    mesh = trimesh.load(DEFAULT_OBJECT, force="mesh")
    mesh.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1.0, 0.0, 0.0]))
    path = tmp_path / "mug_y.obj"
    mesh.export(path)
    app = make_app(input=path)
    s = app.controller.state
    assert app.gui.up.value == "+z" and np.allclose(s.result.masks.support.normal, [0, 0, 1])
    app.gui.up.value = "+y"
    s = app.controller.state
    assert s.error == "" and s.params.facemask.up == (0.0, 1.0, 0.0)
    ref = run_pipeline(
        s.cloud, dataclasses.replace(s.params, facemask=FaceMaskParams(up=(0.0, 1.0, 0.0))),
        until="pool",
    )  # fmt: skip
    assert np.array_equal(s.result.pool.T_world_hand, ref.pool.T_world_hand)
    support = s.result.masks.support
    assert np.allclose(support.normal, [0, 1, 0])
    assert support.height == pytest.approx(float(s.cloud.points[:, 1].min()))
    grid = app.server.scene.get_handle_by_name("/table")
    normal = Rotation.from_quat(grid.wxyz, scalar_first=True).apply([0.0, 0.0, 1.0])
    np.testing.assert_allclose(normal, [0.0, 1.0, 0.0], atol=1e-12)
    assert grid.position[1] == pytest.approx(support.height)
    assert app.scene._up == (0.0, 1.0, 0.0)
    eye = np.asarray(app.server.initial_camera.position) - app.server.initial_camera.look_at
    assert eye[1] > 0.3 * np.linalg.norm(eye)  # from above along +y
    # "custom" keeps the direction in use; an unknown one is refused
    app.gui.up.value = "custom"
    assert app.controller.state.params.facemask.up == (0.0, 1.0, 0.0)
    assert app.gui.up.value == "+y"
    with pytest.raises(ValueError, match="up must be one of"):
        app.controller.set_up("up")
