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
