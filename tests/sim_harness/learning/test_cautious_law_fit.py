"""`benchmarks/cautious_law_fit.py`: the R² a perfect student of the k_sep x S law scores against
the paper's labels, on a recorded dataset."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "benchmarks"))

import cautious_law_fit as clf


def test_the_paper_law_fits_itself_and_a_stronger_separation_fits_less(
    smoke_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "fit.json"
    argv = ["cautious_law_fit.py", "--dataset", str(smoke_dataset), "--split", "train"]
    monkeypatch.setattr(sys, "argv", [*argv, "--scales", "1,1.1,1.3", "--out", str(out)])
    clf.main()
    laws = json.loads(out.read_text())["laws"]
    assert set(laws) == {"1", "1.1", "1.3"}
    for axis in ("x", "y", "z"):
        assert laws["1"]["r2_vs_paper"][axis] == pytest.approx(1.0, abs=1e-6)
        # the further the law is from the paper's, the less of the label it explains
        assert 1.0 > laws["1.1"]["r2_vs_paper"][axis] > laws["1.3"]["r2_vs_paper"][axis]


@pytest.mark.parametrize("text", ["", "1.1,x", "3", "0.2,1.1"])
def test_scales_out_of_range_or_not_numbers_are_refused(text: str) -> None:
    with pytest.raises(SystemExit, match="--scales"):
        clf.parse_scales(text)
