"""Scene files: real Mitsuba scenes that stock integrators render, edited in place through mi.traverse."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from gra_mi.core.errors import GraMiInputError
from gra_mi.stage import scene_keys as keys
from gra_mi.stage.lightstage import default_lightstage, olat_pattern, uniform_pattern
from gra_mi.stage.scene import LightstageScene, render, subject_scene_xml, write_rig
from gra_mi.subject.sequence import save_sequence, tiny_subject

from .conftest import SCENES

TINY = SCENES / "tiny_lightstage.xml"


def test_plain_mitsuba_loads_and_renders_the_scene_file(variant):
    import mitsuba as mi

    scene = mi.load_file(str(TINY), parallel=False, frame="0003")
    params = mi.traverse(scene)
    for i in range(64):
        params[keys.led_intensity(i)] = mi.Color3f(1.0, 1.0, 1.0)
    params.update()
    for integrator in ({"type": "direct"}, {"type": "path", "max_depth": 4}):
        image = np.array(mi.render(scene, sensor=0, integrator=mi.load_dict(integrator), spp=8))
        assert image.shape == (64, 96, 4)
        covered = image[..., 3] > 0.99
        assert covered.mean() > 0.05 and image[..., :3][covered].mean() > 0


def test_scene_exposes_every_key(variant):
    ls = LightstageScene.load(TINY)
    for key in (keys.SUBJECT_POSITIONS, keys.SUBJECT_NORMALS, keys.led_intensity(0), keys.led_position(63)):
        assert key in ls.params
    np.testing.assert_allclose(np.array(ls.params[keys.led_position(5)]).ravel(), ls.stage.led_positions[5], atol=1e-5)
    assert [s.id() for s in ls.scene.sensors()] == [c.name for c in ls.stage.cameras]


def test_set_frame_matches_loading_that_frame(variant, monkeypatch):
    a = LightstageScene.load(TINY, frame=0)
    assert a.set_frame(5) is True
    # Idempotent and free: asking for the current frame neither writes the mesh nor rebuilds the BVH.
    monkeypatch.setattr(a, "params", None)  # any access would fail
    assert a.set_frame(5) is False
    monkeypatch.undo()
    b = LightstageScene.load(TINY, frame=5)
    np.testing.assert_allclose(np.array(a.params[keys.SUBJECT_POSITIONS]), np.array(b.params[keys.SUBJECT_POSITIONS]), atol=1e-6)
    for ls in (a, b):
        ls.set_pattern(uniform_pattern(ls.stage, 0.5))
    np.testing.assert_allclose(render(a, 1, spp=4, seed=3), render(b, 1, spp=4, seed=3), atol=1e-5)


def test_a_moved_mesh_holds_its_own_copy_of_the_frame(variant):
    """Dr.Jit's CPU arrays alias a contiguous NumPy buffer: the mesh must not hold the sequence's memory (a saved
    sequence is its file, mapped read only)."""
    from gra_mi.subject.sequence import MeshSequence

    ls = LightstageScene.load(TINY, frame=0)
    assert isinstance(ls.sequence, MeshSequence)
    ls.set_frame(3)
    before = np.array(ls.params[keys.SUBJECT_POSITIONS])
    if isinstance(ls.sequence.vertices, np.memmap):  # writable stand-in for the check below
        ls.sequence.vertices = np.array(ls.sequence.vertices)
        ls.frame = 0
        ls.set_frame(3)
    ls.sequence.vertices[3] += 1.0
    np.testing.assert_array_equal(np.array(ls.params[keys.SUBJECT_POSITIONS]), before)


def test_lighting_is_linear_in_led_intensities(variant):
    ls = LightstageScene.load(TINY, frame=2)
    images = []
    for pattern in (olat_pattern(ls.stage, 10), olat_pattern(ls.stage, 40), olat_pattern(ls.stage, 10) + olat_pattern(ls.stage, 40)):
        ls.set_pattern(pattern)
        images.append(render(ls, 0, integrator="path", spp=64, seed=1)[..., :3])
    # Deterministic direct lighting from two point lights: the sum of OLATs equals the two lights on together
    # up to sampling noise (path samples one emitter per vertex).
    assert images[0].sum() > 0 and images[1].sum() > 0
    np.testing.assert_allclose(images[2].sum(), images[0].sum() + images[1].sum(), rtol=0.05)


def test_led_count_mismatch_is_reported(tmp_path, variant):
    write_rig(default_lightstage(num_leds=12, num_cameras=2, width=32, height=24), tmp_path / "rig")
    save_sequence(tiny_subject(2), tmp_path / "subject")
    (tmp_path / "scene.xml").write_text(subject_scene_xml("rig", "subject"))
    LightstageScene.load(tmp_path / "scene.xml")  # consistent: loads
    shutil.copy(SCENES / "rigs" / "tiny" / "calibration.json", tmp_path / "rig" / "calibration.json")
    with pytest.raises(GraMiInputError, match="12 LED emitters in the scene but 64 in the calibration"):
        LightstageScene.load(tmp_path / "scene.xml")


def test_malformed_scene_xml(tmp_path, variant):
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene version='3.0.0'><shape type=")
    with pytest.raises(GraMiInputError, match="malformed XML"):
        LightstageScene.load(bad)
    with pytest.raises(GraMiInputError, match="out of range"):
        LightstageScene.load(TINY, frame=99)
