"""`gra-mi view`: the session (relit views for free cameras), the command's bad input, and the page itself in headless
Chromium (screenshots kept in outputs/test-artifacts/viewer/)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gra_mi.apps.viewer_browser import chromium, viewer_in_browser
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import write_exr

from .conftest import SCENES
from .test_cli import run_cli

TINY = SCENES / "tiny_lightstage.xml"
ARTIFACTS = SCENES.parent / "outputs" / "test-artifacts" / "viewer"


def tiny_session(**kw):
    from gra_mi.apps.viewer import ViewerSession, ViewSources

    return ViewerSession(ViewSources(scene=TINY, uv_resolution=64, **kw))


def front_camera(session, width: int = 192, height: int = 128):
    from gra_mi.apps.viewer import camera_pose, viewer_camera

    position, wxyz, fov = camera_pose(session.ls.stage.cameras[0])
    return viewer_camera(position, wxyz, fov, width, height)


def lit_sides(image: np.ndarray, subject: np.ndarray) -> tuple[float, float]:
    """Mean brightness of the subject's left and right halves (split at its middle column)."""
    columns = np.nonzero(subject.any(axis=0))[0]
    middle = (columns[0] + columns[-1]) // 2
    grey = image[..., :3].astype(np.float64).mean(axis=-1)
    left, right = subject.copy(), subject.copy()
    left[:, middle:], right[:, :middle] = False, False
    return float(grey[left].mean()), float(grey[right].mean())


def largest_blob(mask: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    labels, count = ndimage.label(mask)
    sizes = ndimage.sum(mask, labels, range(1, count + 1))
    return labels == 1 + int(np.argmax(sizes))


def test_session_relights_for_a_free_camera(llvm_variant, tmp_path):
    from gra_mi.apps.viewer import camera_pose, viewer_camera, with_lighting

    session = tiny_session()
    assert session.notices and "no fit" in session.notices[0]
    camera = front_camera(session)
    # The page's camera put where a rig camera stands is that camera.
    np.testing.assert_allclose(camera.camera_to_world, session.ls.stage.cameras[0].camera_to_world, atol=1e-9)
    sun = session.render(camera)
    assert sun.image.shape == (128, 192, 3) and {"shade", "rasterize", "tonemap"} <= set(sun.timings)
    with_lighting(session, stage="albedo")
    subject = largest_blob(np.abs(session.render(camera).image.astype(int) - sun.image[0, 0]).sum(axis=-1) > 30)
    assert subject.sum() > 500
    sides = {}
    for x in (-0.8, 0.8):
        with_lighting(session, stage="microfacet", mode="point light", point=(x, 1.2, 0.5))
        sides[x] = lit_sides(session.render(camera).image, subject)
    assert sides[-0.8][0] > sides[-0.8][1] and sides[0.8][1] > sides[0.8][0], sides
    # Highlights follow the view: the shading is for the page's camera position, not a fixed one.
    position, wxyz, fov = camera_pose(session.ls.stage.cameras[0])
    aside = viewer_camera(position + np.array([0.4, 0.0, 0.0]), wxyz, fov, 192, 128)
    shaded = [session.relighter.shade(0, cam, *session.lights())[0] for cam in (camera, aside)]
    assert np.abs(shaded[0].specular - shaded[1].specular).max() > 1e-4
    with_lighting(session, mode="olat", olat=5)
    assert session.lighting_preview().max() > 0 and session.render(camera).image.max() > 0


def test_fast_srgb_is_within_one_level_of_the_exact_curve():
    from gra_mi.apps.viewer import srgb8_fast
    from gra_mi.core.io import to_srgb8

    linear = np.concatenate([np.linspace(0, 1.2, 30000), [np.nan, np.inf, -1.0]]).reshape(-1, 1, 3)
    assert np.abs(srgb8_fast(linear).astype(int) - to_srgb8(linear, 1.0)).max() <= 1


def test_a_long_sequence_s_visibility_is_held_within_the_memory_budget(llvm_variant, tmp_path, monkeypatch):
    """The page traces frames in the background: in memory only as many as the budget holds (the least recently
    used dropped); with a disk cache every frame, read back from disk when shown again."""
    from gra_mi.apps import viewer
    from gra_mi.apps.viewer import with_lighting

    probe = tiny_session()
    frame_bytes = 4 * probe.relighter.atlas.num_texels * -(-probe.ls.stage.num_leds // 32)
    monkeypatch.setattr(viewer, "VISIBILITY_BYTES", 5 * frame_bytes)
    session = tiny_session()
    frames = session.num_frames
    assert frames > 5 and session.frames_to_precompute() == [0, 1, 2, 3, 4]
    assert any("--vis-cache" in note for note in session.notices)
    session.precompute(list(range(frames)), far_field=True)
    assert len(session.relighter.cache._memory) == 5, "the budget, not every frame"
    cached = tiny_session(vis_cache=tmp_path / "vis")
    assert cached.frames_to_precompute() == list(range(frames)) and not any("--vis-cache" in n for n in cached.notices)
    cached.precompute(cached.frames_to_precompute(), far_field=True)
    traced = cached.relighter.cache.misses  # frames of the same pose share their bits
    assert len(cached.relighter.cache._memory) == 5 < traced
    with_lighting(cached, frame=0)
    cached.render(front_camera(cached))  # frame 0 was dropped from memory: read back from disk, not traced
    assert cached.relighter.cache.misses == traced


def test_a_bad_frame_is_said_when_shown_not_read_at_start(llvm_variant, tmp_path):
    """The session checks a frame when it is used (a long sequence starts without a pass over every frame): the
    background trace skips a bad one and says which, and showing it says so too; the other frames render."""
    import shutil

    from gra_mi.apps.viewer import ViewerSession, ViewSources, with_lighting
    from gra_mi.subject.sequence import load_sequence

    shutil.copytree(SCENES, tmp_path / "scenes", ignore=shutil.ignore_patterns("body_*", "outputs"))
    subject = tmp_path / "scenes" / "subjects" / "tiny"
    seq = load_sequence(subject)
    vertices = np.array(seq.vertices)
    vertices[3, 5] = np.nan  # as another tool might write it
    np.savez(subject / "sequence.npz", faces=seq.faces, uvs=seq.uvs, vertices=vertices, normals=np.asarray(seq.normals))
    session = ViewerSession(ViewSources(scene=tmp_path / "scenes" / "tiny_lightstage.xml", uv_resolution=64))
    skipped = session.precompute(list(range(session.num_frames)), far_field=True)
    assert len(skipped) == 1 and "frame 3" in skipped[0] and "sequence.npz" in skipped[0]
    with_lighting(session, frame=3)
    with pytest.raises(GraMiInputError, match="frame 3"):
        session.render(front_camera(session))
    with_lighting(session, frame=4)
    assert session.render(front_camera(session)).image.std() > 1  # the subject, not a blank page


def test_session_refuses_what_it_does_not_have_and_keeps_its_lighting(llvm_variant, tmp_path):
    from gra_mi.apps.viewer import with_lighting

    (tmp_path / "broken.exr").write_bytes(b"not an exr")
    (tmp_path / "rn").mkdir()
    (tmp_path / "rn" / "relightnet.json").write_text('{"format": "something-else/9"}')
    session = tiny_session(envmaps=[tmp_path / "broken.exr"], relightnet=tmp_path / "rn")
    assert any(n.startswith("RelightNet not available") for n in session.notices) and "relightnet" not in session.stages
    before = session.lighting
    with pytest.raises(GraMiInputError, match="broken.exr"):
        with_lighting(session, envmap="broken")
    assert session.lighting == before
    for bad in ({"stage": "relightnet"}, {"frame": 99}, {"mode": "area"}, {"olat": 10_000}, {"envmap": "/etc/passwd"}):
        with pytest.raises(GraMiInputError):
            with_lighting(session, **bad)
    assert session.lighting == before


def test_session_on_a_capture_with_its_fit(path_traced_fit, llvm_variant):
    from gra_mi.apps.viewer import ViewerSession, ViewSources, with_lighting

    cap, fit = path_traced_fit / "cap", path_traced_fit / "fit"
    session = ViewerSession(ViewSources(scene=cap / "scene.xml", capture=cap, fit=fit))
    assert not session.notices and "confidence" in session.stages
    assert any(isinstance(source, Path) for source in session.envmap_sources.values()), "the capture's own maps are offered"
    camera = session.capture.eval_cameras[0]
    truth = session.ground_truth(camera, session.capture.frames[0].mesh_frame)
    assert truth is not None and truth[0].dtype == np.uint8 and truth[0].max() > 0
    with_lighting(session, stage="confidence")
    assert session.render(front_camera(session)).image.max() > 0


def test_view_command_bad_input(tmp_path):
    import socket

    none = run_cli("view")
    assert none.returncode == 2 and "give one of" in none.stderr
    empty = run_cli("view", str(tmp_path))
    assert empty.returncode == 2 and "not a run folder" in empty.stderr
    for flag, value in (("--port", "0"), ("--port", "70000"), ("--max-size", "3"), ("--uv-resolution", "2"), ("--max-size", "nan")):
        bad = run_cli("view", "--scene", str(TINY), flag, value, "--seconds", "1")
        assert bad.returncode == 2 and flag in bad.stderr and "Traceback" not in bad.stderr, (flag, value, bad.stderr)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        taken = run_cli("view", "--scene", str(TINY), "--port", str(port), "--seconds", "1")
    assert taken.returncode == 2 and "--port" in taken.stderr and "cannot listen" in taken.stderr and "Traceback" not in taken.stderr


def test_view_command_refuses_what_it_would_ignore_or_drop(tmp_path):
    """Options a run folder would ignore, a stage named that cannot load (a notice only for a run's own), a map named
    that is not one, two maps with one name, a non-positive --seconds (which once stopped the page while its visibility
    thread traced: tracebacks from a torn-down Mitsuba and a C++ abort)."""
    (tmp_path / "run" / "capture").mkdir(parents=True)
    (tmp_path / "run" / "capture" / "capture.json").write_text("{}")
    write_exr(tmp_path / "square.exr", np.ones((8, 8, 3), np.float32))
    (tmp_path / "empty").mkdir()
    cases = [
        (["view", str(tmp_path / "run"), "--relightnet", str(tmp_path / "empty")], "--relightnet", "run folder brings its own"),
        (["view", "--scene", str(TINY), "--fit", str(tmp_path / "empty")], "empty", "not a fit folder"),
        (["view", "--scene", str(TINY), "--relightnet", str(tmp_path / "empty")], "relightnet.json", "not found"),
        (["view", "--scene", str(TINY), "--envmap", str(tmp_path / "square.exr")], "square.exr", "twice as wide"),
        (["view", "--scene", str(TINY), "--envmap", "a/sky.exr", "--envmap", "b/sky.exr"], "--envmap", "both named 'sky'"),
        (["view", "--scene", str(TINY), "--seconds", "0"], "--seconds", "> 0"),
        (["view", "--scene", str(TINY), "--host", "no such host"], "--host", "not an address"),
    ]
    for argv, *said in cases:
        out = run_cli(*argv, "--seconds", "1") if "--seconds" not in argv else run_cli(*argv)
        assert out.returncode == 2 and all(s in out.stderr for s in said) and "Traceback" not in out.stderr, (argv, out.stderr)


def test_closing_the_page_waits_for_its_threads(llvm_variant):
    """Closed at once, the page joins its visibility thread (which was still tracing when Python exited)."""
    import socket

    from gra_mi.apps.viewer_page import ViewerPage

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    page = ViewerPage(tiny_session(), port=port)
    assert any(w.name == "visibility" for w in page.workers)
    page.close()
    assert not any(w.is_alive() for w in page.workers)


# ------------------------------------------------------------------------------------------------ in a real browser


@pytest.mark.skipif(chromium() is None, reason="needs chromium and chromedriver (scripts/setup.sh installs them with apt)")
def test_the_page_in_headless_chromium():
    """The page loads with the subject, and its controls relight it: another envmap changes the subject's pixels, and
    the lit side follows a point light moved from left to right."""
    from selenium.webdriver.common.keys import Keys

    with viewer_in_browser(TINY, 64) as page:
        latencies = {}
        latencies["stage"] = page.settle(page.choose("show", "albedo"))
        albedo = page.shot(ARTIFACTS / "albedo.png")
        background = np.median(albedo[:, :600].reshape(-1, 3), axis=0)
        subject = np.zeros(albedo.shape[:2], bool)
        subject[:, :600] = np.abs(albedo[:, :600].astype(int) - background).sum(axis=-1) > 60  # the canvas, left of the panel
        subject = largest_blob(subject)  # the torso: not the arm, the LEDs' dots or the axes icon
        assert subject.sum() > 2000, "the subject is on the page"
        latencies["microfacet"] = page.settle(page.choose("show", "microfacet"))
        sun = page.shot(ARTIFACTS / "envmap_sun.png")
        latencies["envmap"] = page.settle(page.choose("envmap", "night"))
        night = page.shot(ARTIFACTS / "envmap_night.png")
        change = np.abs(sun.astype(int) - night.astype(int)).sum(axis=-1)[subject].mean()
        assert change > 10, f"another envmap must relight the subject (mean change {change:.1f})"
        page.settle(page.choose("mode", "point light"))
        latencies["point_left"] = page.settle(page.press("point light (m)", Keys.ARROW_DOWN, 28))  # x: 0.6 → -0.8
        left = lit_sides(page.shot(ARTIFACTS / "point_light_left.png"), subject)
        latencies["point_right"] = page.settle(page.press("point light (m)", Keys.ARROW_UP, 32))  # x: -0.8 → 0.8
        right = lit_sides(page.shot(ARTIFACTS / "point_light_right.png"), subject)
        assert left[0] > left[1] and right[1] > right[0], f"the lit side follows the light: left {left}, right {right}"
        (ARTIFACTS / "latency.json").write_text(json.dumps({k: round(1000 * v) for k, v in latencies.items()}, indent=1))
