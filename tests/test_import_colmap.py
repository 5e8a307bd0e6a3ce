"""`gra-mi import colmap`: a rig calibrated with COLMAP, its model written by COLMAP itself (pycolmap, text and binary),
each camera's frames in its own folder. The imported cameras put the mesh where COLMAP's own projection puts it; a lens
the model states is undone; a model a user could hand over broken stops with one line naming the file and the field."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gra_mi.cli.main import main

from .test_import import write_easymocap

pycolmap = pytest.importorskip("pycolmap")


def write_colmap(native, folder: Path, frames: list, model: str = "PINHOLE", dist=None, binary: bool = False, prefix: str = "",
                 moved=None):  # fmt: skip
    """The rig of the capture ``native`` as COLMAP holds it after calibrating it (one registered image per camera, named
    ``<prefix><cam>/000000.png``; pixel centres at +½, as gra-mi's), written by pycolmap into ``folder/sparse/0``, and each
    camera's frames (taken through OpenCV's ``dist``, the model's own lens where it states one) in ``images/<cam>/``.
    ``moved``: a pycolmap.Sim3d that takes the model out of the LEDs' frame into one of its own (as a reconstruction is)."""
    from scipy.spatial.transform import Rotation

    from gra_mi.stage.lightstage import load_calibration

    write_easymocap(native, folder, frames, None if dist is None else np.asarray(dist, float))
    for name in ("intri.yml", "extri.yml"):
        (folder / name).unlink()
    reconstruction = pycolmap.Reconstruction()
    for k, cam in enumerate(load_calibration(native.folder / "rig" / "calibration.json").cameras):
        camera = pycolmap.Camera.create_from_model_name(k + 1, model, cam.fx, cam.width, cam.height)
        camera.params = [cam.fx, cam.fy, cam.cx, cam.cy, *([] if dist is None else dist)]
        reconstruction.add_camera_with_trivial_rig(camera)
        rot = cam.rotation.T  # world-to-camera
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(Rotation.from_matrix(rot).as_quat()), -rot @ cam.position)
        reconstruction.add_image_with_trivial_frame(
            pycolmap.Image(name=f"{prefix}{k + 1:02d}/000000.png", camera_id=k + 1, image_id=k + 1), pose
        )
    if moved is not None:
        reconstruction.transform(moved)
    (folder / "sparse" / "0").mkdir(parents=True)
    (reconstruction.write_binary if binary else reconstruction.write_text)(str(folder / "sparse" / "0"))
    return reconstruction


@pytest.fixture(scope="module")
def inputs(path_traced_fit, tmp_path_factory):
    """The native capture, and the mesh folder, LEDs and lighting file a COLMAP rig's import is given."""
    from gra_mi.capture.dataset import Capture
    from gra_mi.capture.source_files import write_obj, write_points
    from gra_mi.stage.lightstage import load_calibration
    from gra_mi.subject.sequence import load_sequence

    root = tmp_path_factory.mktemp("colmap_inputs")
    native = Capture.load(path_traced_fit / "cap")
    stage, seq = load_calibration(native.folder / "rig" / "calibration.json"), load_sequence(native.folder / "subject")
    frames = [native.frames[k] for k in (0, 1, len(native.frames) - 1)]
    (root / "meshes").mkdir()
    for k in range(seq.num_frames):
        write_obj(root / "meshes", seq.vertices[k], seq.uvs, seq.faces, None)
        (root / "meshes" / "model.obj").rename(root / "meshes" / f"frame_{k:04d}.obj")
    write_points(root / "leds.pc", stage.led_positions)
    lighting = [{"frame": f.frame, "split": f.split} | ({"uniform": 0.5} if f.kind == "uniform" else {"envmap": str(native.folder / f.envmap)})
                for f in frames]  # fmt: skip
    (root / "lighting.json").write_text(json.dumps({"frames": lighting}))
    args = [
        "--mesh",
        str(root / "meshes"),
        "--leds",
        str(root / "leds.pc"),
        "--lighting",
        str(root / "lighting.json"),
        "--uv-resolution",
        "32",
    ]
    return native, seq, frames, args


@pytest.mark.parametrize("binary", [False, True], ids=["text", "binary"])
def test_a_colmap_rig_imports_where_colmap_projects_it(inputs, tmp_path, binary):
    """The model in either of COLMAP's formats (its image names relative to images/, or to the rig's folder): the imported cameras put the subject's vertices where COLMAP's own
    projection (pycolmap's Image.project_point) puts them in the model's frame, within a thousandth of a pixel; the
    mesh lies on every camera's mask; the lightings are the ones the file names."""
    from gra_mi.capture.dataset import Capture
    from gra_mi.stage.lightstage import load_calibration

    native, seq, frames, args = inputs
    reconstruction = write_colmap(native, tmp_path / "rig", frames, binary=binary, prefix="images/" if binary else "")
    out = tmp_path / "imported"
    assert main(["import", "colmap", str(tmp_path / "rig"), "--out", str(out), *args]) == 0
    report = json.loads((out / "import_report.json").read_text())
    assert [c["camera"] for c in report["cameras"]] == [f"{k + 1:02d}" for k in range(len(reconstruction.images))]
    assert all(c["mask_iou"] >= 0.97 for c in report["cameras"]), report["cameras"]
    assert [f.pose for f in Capture.load(out).frames] == [f.frame for f in frames]
    moved = np.array(json.loads((out / "capture.json").read_text())["source"]["transform"])
    vertices = seq.vertices[0].astype(np.float64)
    for k, camera in enumerate(load_calibration(out / "rig" / "calibration.json").cameras):
        expected = np.array([reconstruction.images[k + 1].project_point(v) for v in vertices])
        np.testing.assert_allclose(camera.project(vertices @ moved[:3, :3].T + moved[:3, 3])[:, :2], expected, atol=1e-3)


def test_a_lens_the_model_states_is_undone(inputs, tmp_path):
    """A binary model of OPENCV cameras (k1, k2, p1, p2) whose images were taken through that lens: the import undoes
    it, and the images match the pinhole truth about as closely as a pinhole rig's (8-bit PNGs, two bilinear
    resamplings), the mesh on the masks."""
    from gra_mi.capture.dataset import Capture, load_observation

    native, _, frames, args = inputs
    (tmp_path / "one.json").write_text(json.dumps({"frames": [{"frame": frames[0].frame, "uniform": 0.5}]}))
    args = [*args[:4], "--lighting", str(tmp_path / "one.json"), *args[6:]]
    errors = {}
    for name, model, dist in (("pinhole", "PINHOLE", None), ("lens", "OPENCV", [-0.12, 0.05, 0.002, -0.003])):
        write_colmap(native, tmp_path / name, frames[:1], model, dist, binary=True)
        out = tmp_path / f"{name}_out"
        assert main(["import", "colmap", str(tmp_path / name), "--out", str(out), *args]) == 0
        report, capture = json.loads((out / "import_report.json").read_text()), Capture.load(out)
        assert all(c["mask_iou"] >= 0.97 for c in report["cameras"]), report["cameras"]
        assert all((c["lens"] is None) == (dist is None) for c in report["cameras"])
        errors[name] = []
        for k in range(len(report["cameras"])):
            a, b = load_observation(capture, f"{k + 1:02d}", 0), load_observation(native, f"cam{k:02d}", frames[0].frame)
            inside, seen, truth = b[..., 3] > 0.99, np.clip(a[..., :3], 0, 1), np.clip(b[..., :3], 0, 1)
            errors[name].append(float(np.abs(seen - truth)[inside].mean() / truth[inside].mean()))
    assert max(errors["lens"]) < max(errors["pinhole"]) + 0.015, errors


def _model_text(folder: Path, kind: str) -> str:
    return (folder / "sparse" / "0" / f"{kind}.txt").read_text()


def test_a_broken_colmap_rig_stops_with_one_line(inputs, tmp_path, capsys):
    """Each way a user's COLMAP rig can be wrong stops the import before anything is written, with one line naming
    the file and what was expected: no model, a camera model gra-mi does not read, a wrong count of parameters, a
    pose of NaN, an image of a camera the model lacks, a name that climbs out of the folder, one camera registered
    at two places, images of another size than the model's, a truncated binary file, a camera without images, a
    camera folder the model does not register."""
    from .test_bad_input import assert_refused

    native, _, frames, args = inputs
    rig, out = tmp_path / "rig", tmp_path / "out"
    write_colmap(native, rig, frames)
    cameras, images = _model_text(rig, "cameras"), _model_text(rig, "images")
    line = next(t for t in images.splitlines() if t and not t.startswith("#"))
    fields = line.split()
    camera = next(t for t in cameras.splitlines() if t.startswith("1 "))
    _, _, width, height, *params = camera.split()
    moved = " ".join(["999", *fields[1:5], str(float(fields[5]) + 0.5), *fields[6:9], "01/000001.png"])
    cases = [
        (cameras.replace(camera, f"1 FOV {width} {height} {' '.join(params)} 0.1"), images, ["cameras.txt", "camera 1", "FOV is not one gra-mi reads"]),
        (cameras.replace(camera, f"1 OPENCV {width} {height} {' '.join(params)}"), images, ["cameras.txt", "camera 1", "OPENCV has 8 parameters"]),
        (cameras.replace(camera, f"1 PINHOLE {width} {height} {params[0]} inf {' '.join(params[2:])}"), images, ["cameras.txt", "camera 1.params[1]", "finite"]),
        (cameras, images.replace(line, " ".join([fields[0], "nan", *fields[2:]])), ["images.txt", "quaternion", "finite"]),
        (cameras, images.replace(line, " ".join([fields[0], "0", "0", "0", "0", *fields[5:]])), ["images.txt", "quaternion cannot be 0"]),
        (cameras, images.replace(line, " ".join([*fields[:8], "99", fields[9]])), ["images.txt", "camera 99"]),
        (cameras, images.replace(line, " ".join([*fields[:9], "../000000.png"])), ["images.txt", "relative folder"]),
        (cameras, images + moved + "\n\n", ["images.txt", "'01/000001.png' and '01/000000.png'", "a rig's camera stays still"]),
        (cameras.replace(camera, f"1 PINHOLE {2 * int(width)} {2 * int(height)} {' '.join(params)}"), images, ["images/01", "resize"]),
    ]  # fmt: skip
    for text_cameras, text_images, needles in cases:
        (rig / "sparse" / "0" / "cameras.txt").write_text(text_cameras)
        (rig / "sparse" / "0" / "images.txt").write_text(text_images)
        assert_refused(["import", "colmap", rig, "--out", out, *args], capsys, *needles, out=out)
    assert_refused(["import", "colmap", tmp_path / "nothing", "--out", out, *args], capsys, "no COLMAP model", out=out)
    binary = tmp_path / "binary"
    write_colmap(native, binary, frames[:1], binary=True)
    data = (binary / "sparse" / "0" / "images.bin").read_bytes()
    (binary / "sparse" / "0" / "images.bin").write_bytes(data[: len(data) // 2])
    assert_refused(["import", "colmap", binary, "--out", out, *args], capsys, "images.bin", "truncated", out=out)
    (binary / "sparse" / "0" / "images.bin").write_bytes(data)
    for path in (binary / "images" / "02").iterdir():
        path.unlink()
    assert_refused(["import", "colmap", binary, "--out", out, *args], capsys, "images/02", "no images", out=out)
    (binary / "images" / "02").rmdir()
    (binary / "images" / "extra").mkdir()
    (binary / "images" / "02").mkdir()
    (binary / "images" / "extra" / "000000.png").write_bytes((binary / "images" / "01" / "000000.png").read_bytes())
    assert_refused(["import", "colmap", binary, "--out", out, *args], capsys, "images", "extra: no image of the model", out=out)


@pytest.mark.parametrize(
    "model, params",
    [
        ("SIMPLE_PINHOLE", [420.0, 110.5, 150.25]),
        ("PINHOLE", [420.0, 380.0, 110.5, 150.25]),
        ("SIMPLE_RADIAL", [420.0, 110.5, 150.25, -0.08]),
        ("RADIAL", [420.0, 110.5, 150.25, -0.08, 0.02]),
        ("OPENCV", [420.0, 380.0, 110.5, 150.25, -0.1, 0.03, 0.002, -0.001]),
        ("FULL_OPENCV", [420.0, 380.0, 110.5, 150.25, -0.1, 0.03, 0.002, -0.001, 0.01, 0.05, 0.01, 0.002]),
        ("OPENCV_FISHEYE", [420.0, 380.0, 110.5, 150.25, 0.05, -0.01, 0.002, -0.0005]),
    ],
)
def test_each_camera_model_images_a_point_where_colmap_does(model, params):
    """gra-mi's camera of each COLMAP model (its K and lens) images points of the camera's frame at the pixel COLMAP's
    own model (pycolmap's Camera.img_from_cam) gives, out to the image's corners."""
    from gra_mi.capture.colmap import ColmapCamera, ColmapImage, calib_camera

    camera = ColmapCamera(camera_id=1, model=model, width=216, height=312, params=params)
    image = ColmapImage(image_id=1, quaternion=[1.0, 0.0, 0.0, 0.0], translation=[0.0, 0.0, 0.0], camera_id=1, name="cam/0.png")
    calib = calib_camera(Path("cameras.txt"), camera, image)
    k = calib.k_matrix(camera.width)
    rng = np.random.default_rng(0)
    xy = rng.uniform([-0.25, -0.4], [0.25, 0.4], (200, 2))  # normalized: about the image's extent
    distorted = xy if calib.lens is None else calib.lens.distort(xy)
    ours = distorted @ k[:2, :2].T + k[:2, 2]
    reference = pycolmap.Camera.create_from_model_name(1, model, 1.0, camera.width, camera.height)
    reference.params = params
    np.testing.assert_allclose(ours, reference.img_from_cam(np.c_[xy, np.ones(len(xy))]), atol=1e-6)


def test_a_model_kept_elsewhere_is_part_of_the_run(inputs, tmp_path, capsys):
    """--colmap-model outside the rig's folder: the same import again finds the capture complete; the model's cameras
    edited before a rerun are another run, refused with the difference named (not resumed on stale intrinsics); an
    --out inside the rig's folder is refused."""
    import shutil

    from .test_bad_input import assert_refused

    native, _, frames, args = inputs
    write_colmap(native, tmp_path / "rig", frames[:1])
    shutil.move(tmp_path / "rig" / "sparse" / "0", tmp_path / "model")
    (tmp_path / "one.json").write_text(json.dumps({"frames": [{"frame": frames[0].frame, "uniform": 0.5}]}))
    args = [*args[:4], "--lighting", str(tmp_path / "one.json"), *args[6:], "--colmap-model", str(tmp_path / "model")]
    command = ["import", "colmap", str(tmp_path / "rig"), "--out", str(tmp_path / "cap"), *args]
    assert main(command) == 0 and main(command) == 0
    cameras = (tmp_path / "model" / "cameras.txt").read_text()
    line = next(t for t in cameras.splitlines() if t.startswith("1 "))
    fields = line.split()
    (tmp_path / "model" / "cameras.txt").write_text(
        cameras.replace(line, " ".join([*fields[:4], str(float(fields[4]) * 1.01), *fields[5:]]))
    )
    assert_refused(command, capsys, "made by another run", "files outside the source")
    assert_refused([*command[:4], str(tmp_path / "rig" / "images" / "cap"), *args], capsys, "--out")


def _own_frame():
    """A similarity out of the LEDs' frame, as a reconstruction's frame is: scaled, turned about a slanted axis, moved."""
    from scipy.spatial.transform import Rotation

    return pycolmap.Sim3d(0.37, pycolmap.Rotation3d(Rotation.from_rotvec([0.6, -1.1, 0.4]).as_quat()), [[2.5], [-1.0], [0.7]])


def test_a_model_in_its_own_frame_is_aligned_to_the_leds(inputs, tmp_path, capsys):
    """A model in a frame and scale of its own (a reconstruction's) with --align-cameras, COLMAP model_aligner's file
    of where its images' cameras are in the LEDs' frame: the imported cameras put the subject's vertices where COLMAP's
    own alignment of the model to those places (pycolmap's align_reconstruction_to_locations) projects them, within a
    thousandth of a pixel; the mesh lies on the masks; the report says the scale the fit found. The places edited
    before a rerun are another run, refused (not resumed on the old alignment)."""
    from gra_mi.stage.lightstage import load_calibration

    from .test_bad_input import assert_refused

    native, seq, frames, args = inputs
    reconstruction = write_colmap(native, tmp_path / "rig", frames[:1], moved=_own_frame())
    (tmp_path / "one.json").write_text(json.dumps({"frames": [{"frame": frames[0].frame, "uniform": 0.5}]}))
    args = [*args[:4], "--lighting", str(tmp_path / "one.json"), *args[6:]]
    truth = load_calibration(native.folder / "rig" / "calibration.json").cameras
    names = [f"{k + 1:02d}/000000.png" for k in range(3)]  # three cameras placed are enough
    (tmp_path / "places.txt").write_text("# image X Y Z\n" + "".join(f"{n} {' '.join(f'{x:.17g}' for x in c.position)}\n"
                                                                    for n, c in zip(names, truth, strict=False)))  # fmt: skip
    out = tmp_path / "imported"
    assert main(["import", "colmap", str(tmp_path / "rig"), "--out", str(out), *args, "--align-cameras", str(tmp_path / "places.txt")]) == 0
    options = pycolmap.RANSACOptions(max_error=1e-3)
    placed = np.array([c.position for c in truth[:3]])
    reconstruction.transform(pycolmap.align_reconstruction_to_locations(reconstruction, names, placed, 3, options))
    report = json.loads((out / "import_report.json").read_text())
    assert all(c["mask_iou"] >= 0.97 for c in report["cameras"]), report["cameras"]
    assert report["alignment"]["scale"] == pytest.approx(1 / 0.37, rel=1e-6) and report["alignment"]["max"] < 1e-6
    assert "Only 3 cameras placed" in (out / "import_report.md").read_text()  # (too few to trust: said)
    remeasured = truth[0].position + [2e-4, 0.0, 0.0]  # a place measured again before a rerun: another run, not a resume
    (tmp_path / "places.txt").write_text("".join(f"{n} {' '.join(f'{x:.17g}' for x in p)}\n"
                                                 for n, p in zip(names, [remeasured, truth[1].position, truth[2].position], strict=True)))  # fmt: skip
    assert_refused(["import", "colmap", tmp_path / "rig", "--out", out, *args, "--align-cameras", tmp_path / "places.txt"], capsys,
                   "made by another run", "files outside the source")  # fmt: skip
    moved = np.array(json.loads((out / "capture.json").read_text())["source"]["transform"])
    vertices = seq.vertices[0].astype(np.float64)
    for k, camera in enumerate(load_calibration(out / "rig" / "calibration.json").cameras):
        expected = np.array([reconstruction.images[k + 1].project_point(v) for v in vertices])
        np.testing.assert_allclose(camera.project(vertices @ moved[:3, :3].T + moved[:3, 3])[:, :2], expected, atol=1e-3)


def test_a_mesh_tracked_in_the_models_frame_moves_with_it(inputs, tmp_path, capsys):
    """The meshes in the model's own frame too (tracked with its calibration, as EasyMocap's and a COLMAP
    reconstruction's are) and --mesh-frame calibration: they move with the cameras, the subject lands where it stands
    among the LEDs (its vertices within 10 µm) and on every mask. Without the option the masks' check fails and names
    it as the likely mistake (the IoU it would reach), or, where the mesh would lie on its side, as the way it stands;
    the option without --align-cameras is refused."""
    from scipy.spatial import cKDTree

    from gra_mi.capture.source_files import write_obj
    from gra_mi.stage.lightstage import load_calibration
    from gra_mi.subject.sequence import load_sequence

    from .test_bad_input import assert_refused

    native, seq, frames, args = inputs
    write_colmap(native, tmp_path / "rig", frames[:1], moved=_own_frame())
    (tmp_path / "one.json").write_text(json.dumps({"frames": [{"frame": frames[0].frame, "uniform": 0.5}]}))
    matrix = np.asarray(_own_frame().matrix())  # s R | t
    (tmp_path / "meshes").mkdir()
    write_obj(tmp_path / "meshes", seq.vertices[0].astype(np.float64) @ matrix[:, :3].T + matrix[:, 3], seq.uvs, seq.faces, None)
    args = ["--mesh", str(tmp_path / "meshes" / "model.obj"), *args[2:4], "--lighting", str(tmp_path / "one.json"), *args[6:]]
    truth = load_calibration(native.folder / "rig" / "calibration.json").cameras
    (tmp_path / "places.txt").write_text("".join(f"{k + 1:02d} {' '.join(f'{x:.17g}' for x in c.position)}\n" for k, c in enumerate(truth)))
    command = ["import", "colmap", tmp_path / "rig", "--out", tmp_path / "out", *args, "--align-cameras", tmp_path / "places.txt"]
    assert_refused(command, capsys, "likely a mesh tracked in the calibration's own frame (--mesh-frame calibration)", out=tmp_path / "out")
    assert_refused([*command[:-2], "--mesh-frame", "calibration"], capsys, "--mesh-frame", "--align-cameras", out=tmp_path / "out")
    in_leds_frame = [*command[:5], *inputs[3][:2], *command[7:]]  # the meshes where the LEDs are, said to move
    assert_refused(
        [*in_leds_frame, "--mesh-frame", "calibration"],
        capsys,
        "likely a mesh in the LEDs' frame (--mesh-frame leds)",
        out=tmp_path / "out",
    )
    assert main([str(a) for a in command] + ["--mesh-frame", "calibration"]) == 0
    report = json.loads((tmp_path / "out" / "import_report.json").read_text())
    assert all(c["mask_iou"] >= 0.97 for c in report["cameras"]) and report["alignment"]["mesh_moved"], report
    moved = np.array(json.loads((tmp_path / "out" / "capture.json").read_text())["source"]["transform"])
    expected = seq.vertices[0].astype(np.float64) @ moved[:3, :3].T + moved[:3, 3]
    imported = load_sequence(tmp_path / "out" / "subject").vertices[0]
    assert cKDTree(expected).query(imported)[0].max() < 1e-5
    # a model frame that lays the unmoved mesh on its side among the LEDs: the upright check names the same cause
    side = pycolmap.Sim3d(0.5, pycolmap.Rotation3d(np.array([np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4)])), [[0.0], [0.0], [0.0]])
    write_colmap(native, tmp_path / "side", frames[:1], moved=side)
    matrix = np.asarray(side.matrix())
    write_obj(tmp_path / "meshes", seq.vertices[0].astype(np.float64) @ matrix[:, :3].T + matrix[:, 3], seq.uvs, seq.faces, None)
    lying = ["import", "colmap", tmp_path / "side", "--out", tmp_path / "out2", *command[5:]]
    assert_refused(lying, capsys, "lying on its side; likely a mesh tracked in the calibration's own frame", out=tmp_path / "out2")


def test_camera_places_that_cannot_align_a_rig_stop_with_one_line(inputs, tmp_path, capsys):
    """Each way a places file can be wrong stops the import before anything is written, naming the file and the line
    or name: too few cameras, cameras in a line, a name no camera has, one camera placed twice, two cameras' names
    swapped (they cannot both land), NaN, a line without three numbers; a model without --align-cameras in a frame of
    its own fails the masks' check rather than importing a rig that misses its subject, and the error names the option."""
    from gra_mi.stage.lightstage import load_calibration

    from .test_bad_input import assert_refused

    native, _, frames, args = inputs
    rig, out = tmp_path / "rig", tmp_path / "out"
    write_colmap(native, rig, frames[:1], moved=_own_frame())
    (tmp_path / "one.json").write_text(json.dumps({"frames": [{"frame": frames[0].frame, "uniform": 0.5}]}))
    args = [*args[:4], "--lighting", str(tmp_path / "one.json"), *args[6:]]
    at = [c.position for c in load_calibration(native.folder / "rig" / "calibration.json").cameras]
    line = lambda name, p: f"{name} {p[0]} {p[1]} {p[2]}\n"  # noqa: E731
    middle = (at[0] + at[1]) / 2
    cases = [
        (line("01", at[0]) + line("02", at[1]), ["are 2, in a line", "place 3 cameras or more"]),
        (line("01", at[0]) + line("02", at[1]) + line("03/000000.png", 2 * middle - at[0]), ["in a line or nearly"]),
        (line("01", at[0]) + line("02", at[1]) + line("cam07", at[2]), ["places.txt", "'cam07' names no camera", "01, 02"]),
        (line("01", at[0]) + line("01/000000.png", at[0]) + line("03", at[2]), ["'01/000000.png' and '01' both place camera 01"]),
        (line("01", at[0]) + line("01", at[1]) + line("03", at[2]), ["line 2", "'01' is placed twice"]),
        (line("01", at[1]) + line("02", at[0]) + line("03", at[2]) + line("04", at[3]), ["lands", "a camera named for another"]),
        (line("01", at[0]) + "02 nan 0 1\n" + line("03", at[2]), ["line 2", "finite"]),
        (line("01", at[0]) + "02 1.0 2.0\n" + line("03", at[2]), ["line 2", "expected NAME X Y Z"]),
    ]
    for text, needles in cases:
        (tmp_path / "places.txt").write_text(text)
        assert_refused(
            ["import", "colmap", rig, "--out", out, *args, "--align-cameras", tmp_path / "places.txt"], capsys, *needles, out=out
        )
    assert_refused(
        ["import", "colmap", rig, "--out", out, *args], capsys, "mask", "most cameras miss it", "--align-cameras PLACES", out=out
    )


def test_the_written_rig_is_read_by_colmap_where_the_capture_holds_it(inputs, tmp_path):
    """`gra-mi capture --layout colmap`'s model, read by COLMAP's own library (pycolmap), aligned by COLMAP's own
    alignment to places.txt, images the capture's mesh where the capture's cameras do (within a thousandth of a pixel):
    the writer holds COLMAP's conventions, not only gra-mi's reader's."""
    from gra_mi.capture.colmap import write_colmap_rig
    from gra_mi.stage.lightstage import load_calibration

    native, seq, _, _ = inputs
    root = write_colmap_rig(native, tmp_path / "colmap")
    model = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    places = [line.split() for line in (root / "places.txt").read_text().splitlines() if not line.startswith("#")]
    by_camera = {image.name.split("/")[0]: image.name for image in model.images.values()}
    names, located = [by_camera[p[0]] for p in places], np.array([[float(v) for v in p[1:]] for p in places])
    model.transform(pycolmap.align_reconstruction_to_locations(model, names, located, 3, pycolmap.RANSACOptions(max_error=1e-3)))
    vertices = seq.vertices[0].astype(np.float64)
    images = {image.name.split("/")[0]: image for image in model.images.values()}
    for camera in load_calibration(native.folder / "rig" / "calibration.json").cameras:
        expected = camera.project(vertices)[:, :2]
        np.testing.assert_allclose([images[camera.name].project_point(v) for v in vertices], expected, atol=1e-3)
    assert len(list((root / "images" / camera.name).glob("*.exr"))) == len(native.frames)


def test_the_written_lighting_file_drives_the_leds_as_the_capture_did(tmp_path):
    """Each lighting of a capture, as `--layout colmap`'s lighting file states it (uniform, an OLAT as `led`, a pattern
    at another drive copied beside it), read back by the import's own lighting reader: the same LED intensities."""
    from types import SimpleNamespace

    from gra_mi.capture.colmap import _lit
    from gra_mi.capture.dataset import FrameLighting
    from gra_mi.capture.easymocap import lighting_frames
    from gra_mi.capture.importer import _drive
    from gra_mi.stage.lightstage import default_lightstage, olat_pattern, uniform_pattern

    stage = default_lightstage(num_leds=12, num_cameras=2)
    drives = {"olat_003": olat_pattern(stage, 3), "dim_005": olat_pattern(stage, 5, 0.25 * stage.max_led_intensity)}
    drives["mixed"] = uniform_pattern(stage, 0.2) * np.linspace(0.1, 1.0, 12)[:, None]
    (tmp_path / "cap" / "patterns").mkdir(parents=True)
    for name, drive in drives.items():
        (tmp_path / "cap" / "patterns" / f"{name}.json").write_text(json.dumps({"intensities": drive.tolist()}))
    frames = [FrameLighting(0, "train", 0, "uniform", None)]
    frames += [FrameLighting(k + 1, "test", 1, "pattern", None, f"patterns/{name}.json") for k, name in enumerate(drives)]
    entries = [
        {"frame": f.frame, "split": f.split} | _lit(SimpleNamespace(folder=tmp_path / "cap"), stage, f, tmp_path / "rig") for f in frames
    ]
    assert [next(k for k in e if k in ("uniform", "led", "pattern")) for e in entries] == ["uniform", "led", "pattern", "pattern"]
    (tmp_path / "rig" / "lighting.json").write_text(json.dumps({"frames": entries}))
    read = lighting_frames(tmp_path / "rig" / "lighting.json", stage.num_leds)
    expected = [uniform_pattern(stage, 0.5), *drives.values()]
    for (_, _, drive), truth in zip(read, expected, strict=True):
        np.testing.assert_allclose(_drive(stage, drive), truth, rtol=1e-6)
