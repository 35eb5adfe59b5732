"""A hostile rollout file or sidecar is refused in one line naming what it is: a folder, a file that is not Parquet
(whatever its bytes), a sidecar formula that is not STL (whatever its text) - never a traceback, never a caret
display spread over three lines."""

from __future__ import annotations

import json

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from pemviz import stl
from pemviz.io import rollouts as rio
from pemviz.io.rollout_format import RolloutFormatError, RolloutMeta

FUZZ = settings(max_examples=300, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
SIDECAR = {"formula": "G[0,99](d >= 2)", "dt_s": 0.05}


def test_a_folder_is_named_as_one(tmp_path):
    folder = tmp_path / "runs.parquet"
    folder.mkdir()
    with pytest.raises(RolloutFormatError) as info:
        rio.read_rollouts(folder)
    assert str(info.value) == (
        f"{folder}: a folder, not a rollout file; give the NAME.parquet that "
        "`pemviz run --save-rollouts NAME.parquet` writes"
    )


@FUZZ
@given(body=st.binary(max_size=64))
def test_any_bytes_but_parquet_s_are_refused_before_the_sidecar(tmp_path_factory, body):
    assume(not body.startswith(b"PAR1") and not body.startswith(b"RRF"))
    path = tmp_path_factory.mktemp("junk") / "x.parquet"  # no sidecar: the file itself is what is wrong
    path.write_bytes(body)
    with pytest.raises(RolloutFormatError) as info:
        rio.read_rollouts(path)
    found = "an empty file" if not body else f"it starts with {body[:4]!r}"
    assert str(info.value) == (
        f"{path}: not a Parquet file ({found}); `pemviz estimate` reads the Parquet rollout file that "
        "`pemviz run --save-rollouts NAME.parquet` writes"
    )


@FUZZ
@given(text=st.text(alphabet=st.sampled_from(list("GFU[](),0123456789 d>=<!&|-.\t\nav")), max_size=30))
def test_a_sidecar_formula_that_is_not_stl_is_one_line_with_its_column(text):
    try:
        stl.parse(text)
    except stl.STLSyntaxError as exc:
        with pytest.raises(RolloutFormatError) as info:
            RolloutMeta.from_json({**SIDECAR, "formula": text}, "x.rollouts.json")
        message = str(info.value)
        assert "\n" not in message and message.endswith(f"at column {exc.column}")
        assert f"formula {text!r} is not valid STL: {exc.message}" in message
    else:
        assert RolloutMeta.from_json({**SIDECAR, "formula": text}, "x.rollouts.json").formula == text


def test_the_estimate_command_says_it_in_one_line(tmp_path, capsys):
    from pemviz.cli import main

    path = tmp_path / "notes.parquet"
    path.write_text("my notes")
    (tmp_path / "notes.rollouts.json").write_text(json.dumps({**SIDECAR, "formula": "G[0,(d >= "}))
    assert main(["estimate", "--no-record", str(path)]) == 2
    assert capsys.readouterr().err == (
        f"pemviz estimate: error: {path}: not a Parquet file (it starts with b'my n'); `pemviz estimate` reads the "
        "Parquet rollout file that `pemviz run --save-rollouts NAME.parquet` writes\n"
    )
