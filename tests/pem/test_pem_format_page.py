"""The user guide's PEM-format page: its examples write PEMs as a user would from scikit-learn and torch, and
``pemviz run --pem`` runs with them."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from conftest import REPO, run_cli

PAGE = REPO / "docs" / "pem-format.md"


def examples() -> dict[str, str]:
    """The page's Python blocks marked ``<!-- pem-format example: NAME -->``, by NAME."""
    text = PAGE.read_text()
    return dict(re.findall(r"<!-- pem-format example: (\w+) -->\n```python\n(.*?)```", text, re.S))


def test_the_page_has_both_examples():
    assert set(examples()) == {"sklearn", "torch"}


@pytest.mark.parametrize("name, file", [("sklearn", "my_pem.pt"), ("torch", "my_torch_pem.pt")])
def test_a_pem_written_as_the_page_says_loads_and_runs(tmp_path, monkeypatch, name, file):
    from pemviz.pem.store import load_pem

    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the page's code runs without a warning (a convergence warning, a deprecation)
        exec(compile(examples()[name], f"{PAGE.name}:{name}", "exec"), scope)
    pem = load_pem(tmp_path / file)
    # the synthetic detector misses more often far away: the file's PEM says so along the braking scene's gap
    near, far = pem.prob_at_gap(np.array([5.0, 40.0]))
    assert 0.9 < near <= 1.0 and far < near - 0.3, (near, far)
    # the stages alone (--plain-fallback 0): on the torch PEM their weights back no interval, and the default's plain
    # Monte Carlo after them (1,000,000 rollouts, ~1 min of CPU) would check the fallback, not the file
    args = f"run --pem {tmp_path / file} --k 3 --n 100 --n-final 200 --plain-fallback 0 --no-record".split()
    proc = run_cli(*args, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert re.search(
        r"mu_hat = \d\.\d+e-\d+, (95% CI \[|no 95% CI from these weights: p >= \d)", proc.stdout
    ), proc.stdout[-1500:]
    assert "nan" not in proc.stdout


def test_a_pem_of_another_version_is_refused_in_one_line(tmp_path):
    import torch
    from pemviz.pem.store import load_pem, pem_path

    payload = torch.load(pem_path(), weights_only=True)
    payload["version"] = 99
    torch.save(payload, tmp_path / "future.pt")
    proc = run_cli("run", "--pem", str(tmp_path / "future.pt"), "--no-record", cwd=tmp_path)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "version" in proc.stderr and "99" in proc.stderr
    with pytest.raises(ValueError):
        load_pem(tmp_path / "future.pt")
