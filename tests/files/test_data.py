"""pemviz.io.data: locating, fetching (SHA-256 checked, atomic) and validating the KITTI salient files."""

from __future__ import annotations

import contextlib
import functools
import http.server
import shutil
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from pemviz.cli import main as cli_main
from pemviz.core.files import repo_root
from pemviz.io import data

SHARED_DATA = repo_root().parent / "shared" / "data" / "kitti-salient"
needs_shared_data = pytest.mark.skipif(
    not (SHARED_DATA / data.INPUTS_FILE).is_file(), reason=f"KITTI salient files absent from {SHARED_DATA}"
)

INPUT_HEADER = (
    "# Format: <Class Num> <Truncation> <Occlusion> <alpha> <dim_w> <dim_l> <dim_h> <loc_x> <loc_y> <loc_z> <rot_y>\n"
)
LABEL_HEADER = "# Format: <Detected> <bbox cx> <bbox cy> <bbox_w> <bbox_h> <err cx> <err cy> <err w> <err h>\n"
GOOD_INPUT = "0 0.000 0 1.850 1.670 1.870 3.690 -16.530 2.390 58.490 1.570\n"
GOOD_LABEL = "1 762 226 95 161 0 1 -3 -4\n"


@pytest.fixture
def isolated(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """No env var, a fake repository root without ../shared, and an empty user cache under tmp_path."""
    monkeypatch.delenv(data.DATA_DIR_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    fake_root = tmp_path / "clone" / "pemviz-repo"
    fake_root.mkdir(parents=True)
    monkeypatch.setattr(data, "repo_root", lambda: fake_root)
    return tmp_path


def _write_pair(
    folder: Path, inputs: str = INPUT_HEADER + GOOD_INPUT * 3, labels: str = LABEL_HEADER + GOOD_LABEL * 3
) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / data.INPUTS_FILE).write_text(inputs)
    (folder / data.LABELS_FILE).write_text(labels)


# ------------------------------------------------------------------------------------------- locate


def test_user_cache_honours_xdg_cache_home(isolated: Path) -> None:
    assert data.user_cache_dir() == isolated / "cache" / "pemviz" / "kitti-salient"


def test_missing_data_error_names_every_place_searched_and_the_fetch_command(isolated: Path, monkeypatch) -> None:
    monkeypatch.setenv(data.DATA_DIR_ENV, str(isolated / "nowhere"))
    with pytest.raises(data.DataNotFoundError) as info:
        data.find_data_dir()
    msg = str(info.value)
    assert isinstance(info.value, FileNotFoundError)
    assert str(isolated / "nowhere") in msg
    assert str(isolated / "clone" / "shared" / "data" / "kitti-salient") in msg
    assert str(isolated / "cache" / "pemviz" / "kitti-salient") in msg
    assert "pemviz data fetch" in msg
    assert msg.index("nowhere") < msg.index("shared") < msg.index("cache")  # in search order


def test_search_order_env_then_beside_repo_then_cache(isolated: Path, monkeypatch) -> None:
    cache = isolated / "cache" / "pemviz" / "kitti-salient"
    beside = isolated / "clone" / "shared" / "data" / "kitti-salient"
    env = isolated / "env-data"
    _write_pair(cache)
    assert data.find_data_dir() == cache
    _write_pair(beside)
    assert data.find_data_dir() == beside
    _write_pair(env)
    monkeypatch.setenv(data.DATA_DIR_ENV, str(env))
    assert data.find_data_dir() == env


def test_folder_with_only_one_file_is_skipped_and_reported(isolated: Path, monkeypatch) -> None:
    env = isolated / "half"
    env.mkdir()
    (env / data.INPUTS_FILE).write_text(INPUT_HEADER + GOOD_INPUT)
    monkeypatch.setenv(data.DATA_DIR_ENV, str(env))
    with pytest.raises(data.DataNotFoundError, match=f"missing {data.LABELS_FILE}"):
        data.find_data_dir()


@needs_shared_data
def test_real_files_load_with_the_spec_row_count_and_detection_rate(monkeypatch) -> None:
    monkeypatch.delenv(data.DATA_DIR_ENV, raising=False)
    d = data.load_salient_data()
    assert d.inputs.shape == (37498, 11) and d.inputs.dtype == np.float64
    assert d.labels.shape == (37498,)
    assert d.labels.mean() == pytest.approx(0.92770, abs=5e-6)  # spec section 2
    assert d.inputs[0].tolist() == [3, 0.0, 0, -0.2, 1.89, 0.48, 1.2, 1.84, 1.47, 8.41, 0.01]  # first data line


# ---------------------------------------------------------------------------------------- malformed


@pytest.mark.parametrize(
    ("inputs", "labels", "bad_file", "pattern"),
    [
        (
            INPUT_HEADER + GOOD_INPUT + "0 0.0 0 1.0 1.0 1.0\n",
            None,
            data.INPUTS_FILE,
            r"line 3: 6 columns, expected 11",
        ),
        (
            None,
            LABEL_HEADER + GOOD_LABEL * 2 + "2 1 1 1 1 0 0 0 0\n",
            data.LABELS_FILE,
            r"line 4: label 2 is not 0 or 1",
        ),
        (INPUT_HEADER + GOOD_INPUT.replace("58.490", "nan"), None, data.INPUTS_FILE, r"line 2: NaN"),
        (None, LABEL_HEADER + "1 2 3 4 5 6 7 8\n", data.LABELS_FILE, r"line 2: 8 columns, expected 9"),
        (None, LABEL_HEADER + "NaN 2 3 4 5 6 7 8 9\n", data.LABELS_FILE, r"line 2: NaN"),
        (INPUT_HEADER + GOOD_INPUT.replace("1.570", "abc"), None, data.INPUTS_FILE, r"line 2: not a number"),
    ],
)
def test_malformed_file_error_names_file_and_line(tmp_path: Path, inputs, labels, bad_file, pattern) -> None:
    _write_pair(tmp_path, inputs or INPUT_HEADER + GOOD_INPUT * 3, labels or LABEL_HEADER + GOOD_LABEL * 3)
    with pytest.raises(data.DataFormatError, match=pattern) as info:
        data.load_salient_data(tmp_path)
    assert str(tmp_path / bad_file) in str(info.value)


def test_row_count_mismatch_is_an_error(tmp_path: Path) -> None:
    _write_pair(tmp_path, INPUT_HEADER + GOOD_INPUT * 3, LABEL_HEADER + GOOD_LABEL * 2)
    with pytest.raises(data.DataFormatError, match="3 rows but .* has 2"):
        data.load_salient_data(tmp_path)


# -------------------------------------------------------------------------------------------- fetch


@contextlib.contextmanager
def _serve(folder: Path) -> Iterator[str]:
    """A local HTTP server over ``folder`` on a free port of 127.0.0.1; yields its base URL."""

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(folder)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


@needs_shared_data
def test_fetch_from_local_server_verifies_sha256_and_the_files_are_then_found(isolated: Path) -> None:
    with _serve(SHARED_DATA) as url:
        folder = data.fetch(base_url=url)
    assert folder == data.user_cache_dir()
    for name, sha in data.FILE_SHA256.items():
        assert data.sha256_file(folder / name) == sha
    assert sorted(p.name for p in folder.iterdir()) == sorted(data.FILE_SHA256)  # no temp files left
    assert data.find_data_dir() == folder
    assert len(data.load_salient_data()) == 37498


def test_fetch_with_wrong_sha256_raises_and_leaves_no_file(tmp_path: Path) -> None:
    served = tmp_path / "served"
    served.mkdir()
    (served / data.LABELS_FILE).write_text(LABEL_HEADER + GOOD_LABEL)  # not the real file
    dest = tmp_path / "dest"
    with _serve(served) as url, pytest.raises(data.ChecksumError, match="SHA-256") as info:
        data.fetch(dest, base_url=url, files=[data.LABELS_FILE])
    assert data.FILE_SHA256[data.LABELS_FILE] in str(info.value)
    assert not dest.exists()  # not even the folder the fetch created


def test_fetch_http_error_names_url_and_leaves_no_file(tmp_path: Path) -> None:
    (tmp_path / "served").mkdir()
    dest = tmp_path / "dest"
    with _serve(tmp_path / "served") as url, pytest.raises(data.DataError, match=f"{url}/{data.INPUTS_FILE}"):
        data.fetch(dest, base_url=url, files=[data.INPUTS_FILE])
    assert not dest.exists()


def test_offline_fetch_into_the_user_cache_leaves_no_empty_folder(isolated: Path) -> None:
    (isolated / "cache").mkdir()  # $XDG_CACHE_HOME exists; pemviz/kitti-salient below it does not
    with pytest.raises(data.DataError, match="download of"):
        data.fetch(base_url="http://127.0.0.1:1/nowhere", timeout_s=5)
    assert list((isolated / "cache").iterdir()) == []


def test_fetch_keeps_a_correct_existing_file_without_downloading(tmp_path: Path) -> None:
    if not (SHARED_DATA / data.LABELS_FILE).is_file():
        pytest.skip(f"KITTI salient files absent from {SHARED_DATA}")
    dest = tmp_path / "dest"
    dest.mkdir()
    shutil.copy(SHARED_DATA / data.LABELS_FILE, dest / data.LABELS_FILE)
    statuses: list[tuple[str, str]] = []
    # An unreachable URL: a download attempt would fail.
    data.fetch(
        dest, base_url="http://127.0.0.1:9/none", files=[data.LABELS_FILE], on_file=lambda n, s: statuses.append((n, s))
    )
    assert statuses == [(data.LABELS_FILE, "present")]


def test_cli_data_fetch_bad_checksum_exits_1_with_message(tmp_path: Path, capsys) -> None:
    served = tmp_path / "served"
    served.mkdir()
    for name in data.FILE_SHA256:
        (served / name).write_text("tampered\n")
    rc = cli_main(["data", "fetch", "--dest", str(tmp_path / "dest"), "--base-url", _start_and_keep(served)])
    assert rc == 1
    assert "SHA-256" in capsys.readouterr().err
    assert not (tmp_path / "dest").exists()  # nothing left, not even the folder


_SERVERS: list = []


def _start_and_keep(folder: Path) -> str:
    cm = _serve(folder)
    url = cm.__enter__()
    _SERVERS.append(cm)
    return url


@pytest.fixture(autouse=True)
def _stop_servers() -> Iterator[None]:
    yield
    while _SERVERS:
        _SERVERS.pop().__exit__(None, None, None)


def test_cli_data_where_without_data_exits_1_naming_fetch(isolated: Path, capsys) -> None:
    assert cli_main(["data", "where"]) == 1
    assert "pemviz data fetch" in capsys.readouterr().err


def test_cli_data_fetch_rejects_a_non_url_base(tmp_path: Path, capsys) -> None:
    assert cli_main(["data", "fetch", "--dest", str(tmp_path / "d"), "--base-url", "ftp.example"]) == 2
    assert "--base-url" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()
