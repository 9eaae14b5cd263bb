"""One vocabulary: the status and mask bits have one owner and never share a value; the names the
reduction, the CLI and the test matrix use come from one place."""

from __future__ import annotations

import itertools

import numpy as np

from cdpr.analysis import conventions as cv
from cdpr.analysis.balance import mask_words, sample_mask


def test_no_two_status_or_mask_bits_share_a_value() -> None:
    bits = list(cv.MASK_NAMES)
    assert len(bits) == len(set(bits))
    for a, b in itertools.combinations(bits, 2):
        assert a & b == 0, f"{cv.MASK_NAMES[a]} and {cv.MASK_NAMES[b]} overlap"
    for b in bits:
        assert b > 0 and b & (b - 1) == 0, f"{cv.MASK_NAMES[b]} is not a single bit"
    assert len(set(cv.MASK_NAMES.values())) == len(bits)  # no word names two bits
    assert cv.STATUS_ALL == sum(cv.STATUS_NAMES)


def test_every_status_bit_masks_a_sample_under_its_own_word() -> None:
    # the message-level sensor fault (a serial load cell's only fault signal) masks its sample:
    # before, only the five bits below 32 did and a sensor fault passed as a usable sample
    for bit, word in cv.STATUS_NAMES.items():
        m = sample_mask(np.ones(3), status=np.array([0, bit, 0]))
        assert m.tolist() == [0, bit, 0]
        assert mask_words(int(m[1])) == [word]


def test_channel_bits_map_to_status_bits() -> None:
    by_hand = {0: 0, 1: 1, 2: 2, 4: 32, 7: 35, 5: 33}
    for ch, status in by_hand.items():
        assert cv.status_from_channel_bits(ch) == status
    arr = cv.status_from_channel_bits(np.array([[0, 1], [4, 7]]))
    assert arr.tolist() == [[0, 1], [32, 35]] and arr.dtype == np.int64


def test_method_names_are_the_solvers_registered() -> None:
    from cdpr.analysis.tension import METHODS

    assert tuple(METHODS) == cv.TENSION_METHODS
