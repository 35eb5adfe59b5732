"""The user guide's realistic-stack page (docs/realistic-stack.md) runs as written: its scene on the library's camera,
detector and tracker gives the estimate the page prints, and the detections' log-probability and the errors'
log-density it splits add up to the rollouts' log p."""

from __future__ import annotations

import re

import numpy as np

from conftest import REPO


def guide_blocks() -> list[str]:
    text = (REPO / "docs" / "realistic-stack.md").read_text().split("## An example: a pedestrian stepping out", 1)[1]
    return re.findall(r"```python\n(.*?)```", text, re.S)[:2]


def test_the_guides_scene_runs_and_prints_the_estimate_the_page_quotes(capsys):
    scene, split = guide_blocks()
    namespace: dict = {"__name__": "realistic_stack_guide"}
    exec(compile(scene, "docs/realistic-stack.md", "exec"), namespace)
    printed = capsys.readouterr().out.strip()
    page = (REPO / "docs" / "realistic-stack.md").read_text()
    assert printed.startswith("mu_hat = ") and printed in page
    exec(compile(split, "docs/realistic-stack.md", "exec"), namespace)
    parts, batch = namespace["parts"], namespace["batch"]
    assert parts.detections.shape == batch.log_p.shape and (parts.detections <= 0).all()
    assert np.allclose(parts.total, batch.log_p, rtol=1e-12, atol=1e-9)
    assert (parts.errors > 0).any()  # a log-density of errors in metres can be positive: why they are kept apart


def test_the_guides_occlusion_block_prints_what_its_comment_says(capsys):
    text = (REPO / "docs" / "realistic-stack.md").read_text().split("## Objects that hide each other", 1)[1]
    block = re.findall(r"```python\n(.*?)```", text, re.S)[0]
    exec(compile(block, "docs/realistic-stack.md", "exec"), {"__name__": "realistic_stack_occlusion"})
    printed = capsys.readouterr().out.strip()
    assert printed == block.split("visible: ")[1].split("\n")[0] == "0.832 2 False"


def test_the_guides_established_track_block_prints_what_its_comment_says(capsys):
    text = (REPO / "docs" / "realistic-stack.md").read_text().split("## A scene that begins with a track", 1)[1]
    block = re.findall(r"```python\n(.*?)```", text, re.S)[0]
    exec(compile(block, "docs/realistic-stack.md", "exec"), {"__name__": "realistic_stack_established"})
    assert capsys.readouterr().out.strip() == block.split("# ")[-1].strip() == "[ True False] 25.0"


def test_the_guides_state_features_block_prints_what_its_comment_says(capsys):
    """The example's scene names the tracker's state; the page's block reads it back from the example's batch: rollout
    0's track confirmed at step 2 (its second measurement), 2.82 s from the ego then (the checks of
    tests/stack/test_tracker_features.py hold the numbers to hand computation)."""
    scene, split = guide_blocks()
    text = (REPO / "docs" / "realistic-stack.md").read_text().split("## The state the stack acts on", 1)[1]
    block = re.findall(r"```python\n(.*?)```", text, re.S)[0]
    namespace: dict = {"__name__": "realistic_stack_features"}
    for code in (scene, split, block):
        exec(compile(code, "docs/realistic-stack.md", "exec"), namespace)
    printed = capsys.readouterr().out.strip().splitlines()[-1]
    assert printed == block.split("# ")[-1].strip() == "(100, 40, 1, 13) 2 2.82"
    from pemviz.core.features import check_features

    assert check_features(namespace["problem"].features, namespace["batch"], 30) is None
