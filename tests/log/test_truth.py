"""The sim clock's truth file (hil.log.truth): rows matched to the loop by sample counter, whole or refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hil.log.truth import read_truth, truth_path, write_truth


def test_rows_are_matched_by_tick_whatever_their_order(tmp_path: Path) -> None:
    log = tmp_path / "run-1.h5"
    path = write_truth(log, [12, 10, 11], [1.2, 1.0, 1.1], [-1.2, -1.0, -1.1])
    assert path == truth_path(log) == tmp_path / "run-1.truth.npz" and path.is_file()
    assert not list(tmp_path.glob("*.part"))
    y, z = read_truth(log, np.array([11, 12, 10, 11]))
    assert y.tolist() == [1.1, 1.2, 1.0, 1.1] and z.tolist() == [-1.1, -1.2, -1.0, -1.1]


def test_no_file_is_none_and_a_missing_row_is_named(tmp_path: Path) -> None:
    log = tmp_path / "run-2.h5"
    assert read_truth(log, np.array([1, 2])) is None
    write_truth(log, [1, 2, 4], [0.0] * 3, [0.0] * 3)
    with pytest.raises(ValueError, match=r"run-2\.truth\.npz: no truth row for loop tick 3 \(1 of 4 rows missing\)"):
        read_truth(log, np.array([1, 2, 3, 4]))
    with pytest.raises(ValueError, match=r"no truth row for loop tick 5 "):
        read_truth(log, np.array([5]))


def test_a_log_without_loop_rows_has_no_truth_rows_to_match(tmp_path: Path) -> None:
    """A session stopped before its first sample (a pruned trial's cell): empty, not an error."""
    log = tmp_path / "run-3.h5"
    write_truth(log, [], [], [])
    y, z = read_truth(log, np.array([], dtype=np.int64))
    assert y.size == z.size == 0
    write_truth(log, [1, 2], [0.5, 0.6], [0.0, 0.0])
    y, _ = read_truth(log, np.array([], dtype=np.int64))
    assert y.size == 0
