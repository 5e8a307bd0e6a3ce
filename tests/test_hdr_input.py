"""Real HDR environment maps as input: OpenEXR compressions and channel layouts, Radiance .hdr, flux-preserving
downsampling, other tools' orientation conventions, and the flux-conserving repair of lossy-compression ringing.
Every file here is written by the test itself."""

from __future__ import annotations

import logging

import numpy as np
import OpenEXR
import pytest

from gra_mi.cli import main
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import read_exr, read_hdr_image, read_rgbe, write_rgbe
from gra_mi.stage import envmap as em


def sky_with_sun(h: int = 32) -> np.ndarray:
    """A smooth sky plus a bright one-pixel sun: what real HDRIs look like to the loader."""
    d = em.pixel_directions(h, 2 * h)
    env = (0.5 + 0.4 * np.maximum(d[..., 1:2], 0.0)) * np.array([0.6, 0.8, 1.0])
    env[h // 4, h // 3] = [800.0, 700.0, 600.0]
    return env.astype(np.float32)


def flux(env: np.ndarray) -> np.ndarray:
    return (env.astype(np.float64) * em.pixel_solid_angles(*env.shape[:2])[..., None]).sum(axis=(0, 1))


def write_openexr(path, image: np.ndarray, compression, half: bool, interleaved: bool, alpha: bool = False) -> None:
    dtype = np.float16 if half else np.float32
    pixels = np.concatenate([image, np.ones_like(image[..., :1])], axis=-1) if alpha else image
    pixels = pixels.astype(dtype)
    if interleaved:  # the form OpenEXR's Python API returns with separate_channels=False
        channels = {"RGBA" if alpha else "RGB": pixels}
    else:
        channels = {name: np.ascontiguousarray(pixels[..., i]) for i, name in enumerate("RGBA"[: pixels.shape[2]])}
    with OpenEXR.File({"compression": compression, "type": OpenEXR.scanlineimage}, channels) as f:
        f.write(str(path))


@pytest.mark.parametrize(
    "compression",
    [OpenEXR.ZIP_COMPRESSION, OpenEXR.PIZ_COMPRESSION, OpenEXR.DWAA_COMPRESSION, OpenEXR.DWAB_COMPRESSION],
    ids=["zip", "piz", "dwaa", "dwab"],
)
@pytest.mark.parametrize("interleaved", [False, True], ids=["separate", "interleaved"])
@pytest.mark.parametrize("alpha", [False, True], ids=["rgb", "rgba"])
def test_half_float_exr_in_every_compression_and_layout(tmp_path, compression, interleaved, alpha):
    env = sky_with_sun()
    path = tmp_path / "sky.exr"
    write_openexr(path, env, compression, half=True, interleaved=interleaved, alpha=alpha)
    loaded = em.load_envmap(path)
    assert loaded.shape == env.shape and loaded.dtype == np.float32
    lossy = compression in (OpenEXR.DWAA_COMPRESSION, OpenEXR.DWAB_COMPRESSION)
    # half floats keep 3 significant digits; DWA is lossy, so only the flux is held to a tolerance there
    if not lossy:
        np.testing.assert_allclose(loaded, env.astype(np.float16).astype(np.float32), rtol=0, atol=0)
    np.testing.assert_allclose(flux(loaded), flux(env), rtol=0.01 if lossy else 1e-3)


def test_layered_exr_reads_the_first_rgb_layer(tmp_path):
    env = sky_with_sun(8)
    channels = {f"ViewLayer.Combined.{c}": np.ascontiguousarray(env[..., i]) for i, c in enumerate("RGB")}
    channels["ViewLayer.Depth.Z"] = np.ones(env.shape[:2], np.float32)
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels) as f:
        f.write(str(tmp_path / "layers.exr"))
    np.testing.assert_array_equal(read_exr(tmp_path / "layers.exr"), env)


def _rgbe_reference(image: np.ndarray) -> np.ndarray:
    """Radiance's own quantisation, written out independently: 8-bit mantissas sharing the max channel's exponent."""
    peak = image.max(axis=-1, keepdims=True)
    exponent = np.ceil(np.log2(np.maximum(peak, 1e-30)) + 1e-12)
    step = 2.0 ** (exponent - 8)
    return np.where(peak > 1e-30, (np.floor(image / step) + 0.5) * step, 0.0)


def test_radiance_hdr_flat_and_mitsuba_written(tmp_path, llvm_variant):
    import mitsuba as mi

    env = sky_with_sun(16)
    write_rgbe(tmp_path / "flat.hdr", env)
    np.testing.assert_allclose(read_rgbe(tmp_path / "flat.hdr"), _rgbe_reference(env.astype(np.float64)), rtol=1e-6)
    # Mitsuba writes run-length encoded scanlines: an independent writer for the RLE path of the reader.
    mi.Bitmap(env, pixel_format=mi.Bitmap.PixelFormat.RGB).write(str(tmp_path / "rle.hdr"))
    assert (tmp_path / "rle.hdr").stat().st_size < (tmp_path / "flat.hdr").stat().st_size  # it did compress
    rle = read_hdr_image(tmp_path / "rle.hdr")
    np.testing.assert_allclose(rle, env, rtol=2**-7)
    np.testing.assert_allclose(em.load_envmap(tmp_path / "rle.hdr"), rle)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"not an image at all", "not a Radiance HDR file"),
        (b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 4 +X 8\n\x02\x02\x00\x08", "corrupt or truncated"),
        (b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 4 +X 8\n", "32-bit_rle_rgbe"),
        (b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n+Y 4 +X 8\n", "resolution line"),
        (b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y four +X 8\n" + bytes(128), "integer sizes"),
        (b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y -4 +X 8\n" + bytes(128), "must be >= 1"),
        (b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 100000 +X 200000\n" + bytes(128), "corrupt or truncated"),
    ],
)
def test_bad_hdr_files_name_the_file(tmp_path, content, message):
    path = tmp_path / "bad.hdr"
    path.write_bytes(content)
    with pytest.raises(GraMiInputError, match=message) as info:
        em.load_envmap(path)
    assert str(path) in str(info.value)


def test_downsampling_keeps_the_flux_of_an_8k_class_map():
    env = sky_with_sun(512)  # 1024 x 512 stands in for 8k x 4k: the same code, 64x fewer pixels
    small = em.downsample_envmap(env, 64)
    assert small.shape == (64, 128, 3)
    np.testing.assert_allclose(flux(small), flux(env), rtol=1e-6)  # float32 pixels
    # and the LEDs see the same light either way
    stage_dirs = em.pixel_directions(8, 16).reshape(-1, 3)
    np.testing.assert_allclose(em.envmap_irradiance(small, stage_dirs), em.envmap_irradiance(env, stage_dirs), rtol=0.02)


@pytest.mark.parametrize("width", [64, 66])  # a whole-pixel shift and a fractional one
def test_conventions_put_the_sun_where_the_source_tool_shows_it(tmp_path, width):
    """Blender's world texture centres its image on +X (GLSL: u = 0.5 - atan2(y, x) / 2pi); after the Y-up conversion
    (x, y, z)_blender -> (x, z, -y) that is gra-mi's +X, which gra-mi's own convention puts at u = 0.25."""
    h = width // 2
    env = np.full((h, width, 3), 0.01, np.float32)
    env[h // 2, width // 2] = 1000.0  # a sun at the image centre, on the horizon
    path = tmp_path / "centre.exr"
    from gra_mi.core.io import write_exr

    write_exr(path, env)
    for convention, expected in [("mitsuba", [0.0, 0.0, 1.0]), ("blender", [1.0, 0.0, 0.0]), ("threejs", [1.0, 0.0, 0.0])]:
        loaded = em.load_envmap(path, convention=convention)
        brightest = np.unravel_index(np.argmax(loaded[..., 0]), loaded.shape[:2])
        direction = em.pixel_directions(h, width)[brightest]
        assert np.degrees(np.arccos(np.clip(direction @ expected, -1, 1))) < 360.0 / width * 1.01, convention
    # --envmap-rotate turns the light counter-clockwise seen from above, as stage.envmap.rotate does
    turned = em.load_envmap(path, rotate_deg=90.0)
    if width % 4 == 0:
        np.testing.assert_allclose(turned, em.rotate(em.load_envmap(path), em.rotation_y(90.0)))


def test_dwa_ringing_is_repaired_with_flux_kept(caplog):
    """The real map that motivated this: pixels down to -1,876 beside a sun of 11,800."""
    env = sky_with_sun(64)
    y, x = 16, 21
    env[y, x] = 11800.0
    env[y, x - 1] = env[y, x + 1] = -1876.0 / 2
    env[y - 1, x] = -1876.0
    env[y, x + 2] += 1876.0 * 1.5  # the overshoot that goes with the undershoot
    with caplog.at_level(logging.WARNING):
        repaired = em.validate_envmap(env, "real.exr")
    assert repaired.min() >= 0.0
    np.testing.assert_allclose(flux(repaired), flux(env), rtol=1e-6)  # float32 pixels
    assert "negative values (down to -1876" in caplog.text and "flux of each channel kept" in caplog.text
    clamped = np.maximum(env, 0.0)
    assert np.all(flux(clamped) > flux(env) * 1.01)  # what clamping alone would have added
    far = np.ones(env.shape[:2], bool)
    far[y - 4 : y + 5, x - 4 : x + 5] = False
    np.testing.assert_allclose(repaired[far], env[far], rtol=1e-5)  # the rest of the map is untouched


def test_a_sun_whose_colour_compression_destroyed_is_warned_about(tmp_path, caplog):
    """Two real maps had a sun of (0, 0, 11800) after DWA compression, which lights the subject violet. A bright
    source with a channel at exactly zero is warned about, naming the file and the pixel; intact suns (this test's,
    a deep-orange one, the reference maps) are not."""
    from gra_mi.stage.envmap_library import REFERENCE_MAPS, reference_map

    env = sky_with_sun(64)
    env[16, 21] = [0.0, 0.0, 11800.0]
    env[16, 22] = [0.0, 0.0, 9000.0]
    write_openexr(tmp_path / "violet.exr", env, OpenEXR.ZIP_COMPRESSION, half=False, interleaved=False)
    with caplog.at_level(logging.WARNING):
        em.load_envmap(tmp_path / "violet.exr")
    assert "violet.exr: 2 very bright pixel(s) have a colour channel at zero" in caplog.text
    assert "row 16, column 21 = (0, 0, 1.18e+04)" in caplog.text and "lossy (DWA)" in caplog.text
    caplog.clear()
    orange = sky_with_sun(64)
    orange[16, 21] = [11800.0, 2500.0, 40.0]
    intact = [sky_with_sun(64), orange] + [reference_map(name, 64) for name in REFERENCE_MAPS]
    with caplog.at_level(logging.WARNING):
        for k, image in enumerate(intact):
            em.validate_envmap(image, f"intact{k}.exr")
    assert "very bright" not in caplog.text


@pytest.mark.parametrize(
    ("image", "message"),
    [
        (np.zeros((16, 32, 3), np.float32), "no light"),
        (np.ones((16, 30, 3), np.float32), "twice as wide"),
        (np.full((16, 32, 3), np.inf, np.float32), "Inf"),
    ],
)
def test_bad_maps_stop_relight_with_one_line_and_nothing_written(tmp_path, capsys, image, message):
    from gra_mi.core.io import write_exr
    from tests.conftest import SCENES

    path = tmp_path / "bad.exr"
    write_exr(path, image)
    out = tmp_path / "out"
    assert main(["relight", str(SCENES / "tiny_lightstage.xml"), "--envmap", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(path) in err and message in err, err
    assert not out.exists()


def test_corrupt_exr_is_one_line(tmp_path, capsys):
    path = tmp_path / "broken.exr"
    path.write_bytes(b"\x76\x2f\x31\x01" + b"\x00" * 40)
    assert main(["relight", "scene.xml", "--envmap", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "not a readable OpenEXR file" in err and str(path) in err and err.count("\n") == 1


@pytest.mark.parametrize(
    ("option", "message"),
    [(["--envmap-height", "1"], "--envmap-height: must be >= 2"), (["--envmap-rotate", "nan"], "--envmap-rotate: must be a finite number")],
)
def test_bad_envmap_options_name_the_flag(tmp_path, capsys, option, message):
    from gra_mi.core.io import write_exr

    write_exr(tmp_path / "sky.exr", sky_with_sun(8))
    out = tmp_path / "out"
    assert main(["relight", "scene.xml", "--envmap", str(tmp_path / "sky.exr"), *option, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not out.exists()


@pytest.mark.parametrize(
    ("name", "message"), [("maps", "a folder: expected an HDR image file"), ("sky.png", "of type '.png': expected an HDR")]
)
def test_an_envmap_that_is_no_hdr_file_is_named(tmp_path, capsys, name, message):
    """A folder, or an image of another kind, given as the environment map: what it is and what was expected."""
    path = tmp_path / "in" / name
    path.parent.mkdir(parents=True)
    if path.suffix:
        path.write_bytes(b"\x89PNG")
    else:
        path.mkdir()
    out = tmp_path / "out"
    assert main(["relight", "scene.xml", "--envmap", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(path) in err and message in err, err
    assert not out.exists()
