"""Registration of walk-arounds (``process``): frames in their capture order, pairs closing
the loop, and the retry of what the first mapping left out (with stand-in models, no COLMAP)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from plenoctree.process import register, sfm
from plenoctree.process.frames import list_photos, natural_key


def test_frames_numbered_without_zeros_keep_their_capture_order(tmp_path):
    """``IMG_4831_2`` comes before ``IMG_4831_10`` (lexicographic order put _10 … _19 between
    _1 and _2, and the sequential matcher paired frames far apart in time)."""
    for i in (0, 1, 2, 9, 10, 11, 20, 100):
        Image.fromarray(np.full((8, 8, 3), i, np.uint8)).save(tmp_path / f"IMG_4831_{i}.png")
    names = [p.name for p in list_photos(tmp_path)]
    assert names == [f"IMG_4831_{i}.png" for i in (0, 1, 2, 9, 10, 11, 20, 100)]
    padded = ["frame_00010.png", "frame_00002.png", "frame_00100.png"]
    assert sorted(padded, key=natural_key) == sorted(padded)          # padded names: as before
    assert sorted(["b1", "a10", "a2", "a02"], key=natural_key) == ["a02", "a2", "a10", "b1"]


def test_loop_pairs_close_the_walk_around():
    pairs = sfm.loop_pairs(20, 3)
    assert pairs == [(0, 17), (0, 18), (0, 19), (1, 18), (1, 19), (2, 19)]
    assert all(20 - (j - i) <= 3 for i, j in pairs)                   # <= 3 apart round the end
    assert sfm.loop_pairs(4, 3) == [] and len(sfm.loop_pairs(151, 10)) == 55
    matcher, pairs, _ = sfm.plan_matching(sfm.SfmOptions(sequential_overlap=3), 67, True, 4400)
    assert matcher == "sequential" and (0, 66) in pairs and (2, 66) in pairs
    assert set(pairs) == set(sfm.sequential_pairs(67, 3)) | set(sfm.loop_pairs(67, 3))
    assert len(pairs) == len(set(pairs)) and pairs == sorted(pairs)
    _, every, _ = sfm.plan_matching(sfm.SfmOptions(), 20, True, 1000)   # exhaustive: unchanged
    assert len(every) == 190


def test_retry_pairs_nearest_first_round_the_end():
    pairs = register.retry_pairs(64, [44, 45], {(43, 44), (44, 46)}, 3, 100)
    assert (43, 44) not in pairs and (44, 46) not in pairs and len(pairs) == len(set(pairs))
    assert pairs[:3] == [(44, 45), (45, 46), (42, 44)]                 # distance 1, then 2
    assert {j - i for i, j in pairs} == {1, 2, 3}
    assert register.retry_pairs(64, [44, 45], set(), 3, 4) == [(43, 44), (44, 45), (45, 46),
                                                                (42, 44)]     # the limit
    assert set(register.retry_pairs(64, [1], set(), 3, 100)) == {
        (0, 1), (1, 2), (1, 63), (1, 3), (1, 62), (1, 4)}              # frame 63 is next to 0
    assert register.retry_pairs(64, [5], set(), 3, 0) == []
    assert len(register.retry_pairs(6, [0], set(), 30, 100)) == 5      # reach beyond the set


class _Model:
    """Stand-in for a pycolmap.Reconstruction: registered image names."""

    def __init__(self, names):
        self.images = {k + 1: SimpleNamespace(name=n) for k, n in enumerate(names)}

    def num_reg_images(self):
        return len(self.images)

    def reg_image_ids(self):
        return list(self.images)


def _names(n):
    return [f"f{i}.png" for i in range(n)]


def test_retry_matches_the_left_out_frames_and_maps_on_from_the_largest_model():
    names = _names(64)
    models = {1: _Model(names[:44]), 2: _Model(names[45:])}            # split at frame 44
    done = set(sfm.sequential_pairs(64, 2))
    matched, starts = [], []

    def remap(start):
        starts.append(start)
        return {1: _Model(names)}

    out, stats = register.retry_registration(models, names, done, True, 2, matched.append,
                                             remap, max_pairs=1000)
    assert out[1].num_reg_images() == 64 and starts == [models[1]]
    assert stats == {"rounds": 1, "pairs": len(matched[0]), "registered_before": 44,
                     "registered_after": 64, "models_before": 2}
    left = set(range(44, 64))
    assert matched[0] and not set(matched[0]) & done
    assert all(i in left or j in left for i, j in matched[0])
    assert max(min(j - i, 64 - (j - i)) for i, j in matched[0]) <= register.RETRY_REACH * 2
    assert (0, 63) not in done and (0, 63) in matched[0]               # round the end


def test_retry_stops_when_nothing_more_registers_and_keeps_the_models():
    names = _names(40)
    models = {1: _Model(names[:20]), 2: _Model(names[20:30])}
    calls = []

    def remap(start):
        calls.append(start)
        return {1: _Model(names[:20]), 2: _Model(names[20:35])}       # largest not grown

    out, stats = register.retry_registration(models, names, set(), True, 2,
                                             lambda p: calls.append(len(p)), remap, 10)
    assert out is models and stats["rounds"] == 1 and stats["registered_after"] == 20
    assert calls[0] == 10                                             # at most max_pairs


def test_retry_grows_its_reach_and_skips_what_needs_no_retry():
    names = _names(100)
    grown = iter([_Model(names[:80]), _Model(names[:99])])
    matched = []
    out, stats = register.retry_registration(
        {1: _Model(names[:60])}, names, set(), True, 2, matched.append,
        lambda start: {1: next(grown)}, 10_000)
    assert stats["rounds"] == 2 and out[1].num_reg_images() == 99
    reach = [max(min(j - i, 100 - (j - i)) for i, j in m) for m in matched]
    assert reach == [register.RETRY_REACH * 2, 2 * register.RETRY_REACH * 2]
    assert not set(matched[0]) & set(matched[1])                     # no pair matched twice

    def fail(*_):
        raise AssertionError("no retry expected")

    full = {1: _Model(names[:96])}                                    # >= RETRY_FRACTION
    assert register.retry_registration(full, names, set(), True, 2, fail, fail, 100) == (full, {})


def test_retry_of_photos_matched_in_every_pair_only_maps_again():
    names = _names(30)
    starts = []
    out, stats = register.retry_registration(
        {1: _Model(names[:20])}, names, set(), False, 10,
        lambda p: pytest.fail("every pair was matched already"),
        lambda start: starts.append(start) or {1: _Model(names[:28])}, 1000)
    assert stats["pairs"] == 0 and stats["rounds"] == 1 and out[1].num_reg_images() == 28
    assert len(starts) == 1                       # no second round: the same mapping again


def test_retry_is_on_by_default_and_off_with_a_flag(tmp_path, monkeypatch):
    import plenoctree.process as proc
    from plenoctree.cli import main

    seen = []
    monkeypatch.setattr(proc, "process", lambda cfg: seen.append(cfg) or 1 / 0)
    with pytest.raises(ZeroDivisionError):
        main(["process", str(tmp_path), "--out", str(tmp_path / "a")])
    with pytest.raises(ZeroDivisionError):
        main(["process", str(tmp_path), "--out", str(tmp_path / "b"), "--no-retry"])
    assert [c.sfm.retry for c in seen] == [True, False]
