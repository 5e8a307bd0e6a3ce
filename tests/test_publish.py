"""Generated results: the README's headline block is replaced from a run's record, stamped with commit and machine."""

from __future__ import annotations

import pytest

from gra_mi.apps.demo_report import with_block
from gra_mi.core.stamp import run_stamp, stamp_said

from .conftest import REPO


def test_a_block_is_replaced_between_its_markers_only():
    text = "intro\n<!-- headline -->\nold\n<!-- /headline -->\nafter\n"
    assert with_block(text, "headline", ["new 1", "new 2"]) == "intro\n<!-- headline -->\nnew 1\nnew 2\n<!-- /headline -->\nafter\n"
    with pytest.raises(ValueError, match="headline"):
        with_block("no markers", "headline", ["x"])


def test_the_readme_holds_a_stamped_headline_block():
    readme = (REPO / "README.md").read_text()
    block = readme.split("<!-- headline -->", 1)[1].split("<!-- /headline -->", 1)[0]
    assert "commit " in block and "preset " in block and "| stage |" in block


def test_a_stamp_names_the_commit_and_the_machine():
    stamp = run_stamp(preset="tiny", variant="llvm_ad_rgb")
    said = stamp_said(stamp)
    assert said.startswith("commit ") and "preset tiny" in said and "-core" in said and "llvm_ad_rgb" in said


def _demo_record(bounces: int, shift: float) -> dict:
    split = {"psnr": 25.0 + shift, "ssim": 0.9, "brightness": -0.1 + shift / 100}
    pair = {"microfacet": {"psnr": 24.0 + shift}, "relightnet": {"psnr": 25.0 + shift}}
    region = {"albedo_bias": 0.09 - shift / 100, "albedo_rel_median": 0.1, "roughness_mae": 0.03}
    return {
        "stamp": {"commit": "abc1234", "preset": "olat", "machine": "2-core x86_64 (Linux)"},
        "transport": {"bounces": bounces, "bounce_rays": 32},
        "eval": {"stages": {"microfacet": {"splits": {"test1_cam06": split}}, "RelightNet": {"splits": {"test1_cam06": split}}}},
        "relightnet": {"splits": {"novel lighting (OLAT)": pair, "novel view (selection)": pair}},
        "fit": {
            "regions": {"skin": region, "cloth": region},
            "baseline": {"skin": {"roughness_mae": 0.06}, "cloth": {"roughness_mae": 0.06}},
        },
    }


def test_two_demo_runs_side_by_side(tmp_path):
    import json

    from scripts.compare_demos import main

    for name, bounces, shift in (("one", 1, 0.0), ("two", 2, 1.5)):
        (tmp_path / name / "capture" / "images" / "cam00").mkdir(parents=True)
        (tmp_path / name / "capture" / "images" / "cam00" / "0000.exr").write_bytes(b"pixels")
        (tmp_path / name / "demo.json").write_text(json.dumps(_demo_record(bounces, shift)))
    assert main([str(tmp_path / "one"), str(tmp_path / "two"), "--write", str(tmp_path / "page.md")]) == 0
    page = (tmp_path / "page.md").read_text()
    assert "| microfacet | test1_cam06 | 25.00 | 26.50 | +1.50 |" in page and "1 bounce and 2 bounces (smoothing radius 0)" in page
    assert "| novel lighting (OLAT) | 24.00 | 25.00 | +1.00 | 25.50 | 26.50 | +1.00 |" in page and "(selection)" not in page
    assert "images (1 files) are byte-identical" in page and "commits differ" not in page
    # Another capture, another commit: both said.
    (tmp_path / "two" / "capture" / "images" / "cam00" / "0000.exr").write_bytes(b"other pixels")
    later = _demo_record(2, 1.5)
    later["stamp"]["commit"] = "def5678-dirty"
    (tmp_path / "two" / "demo.json").write_text(json.dumps(later))
    assert main([str(tmp_path / "one"), str(tmp_path / "two"), "--write", str(tmp_path / "page.md")]) == 0
    page = (tmp_path / "page.md").read_text()
    assert "are NOT identical" in page and "`git diff abc1234 def5678 -- gra_mi`" in page
    assert "The 2 bounces (smoothing radius 0) run's checkout had uncommitted changes" in page
    other = _demo_record(2, 0.0) | {"stamp": {"commit": "x", "preset": "small"}}
    (tmp_path / "two" / "demo.json").write_text(json.dumps(other))
    assert main([str(tmp_path / "one"), str(tmp_path / "two")]) == 2
    assert main([str(tmp_path / "one"), str(tmp_path / "missing")]) == 2
