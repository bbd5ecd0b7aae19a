"""The shared argument checks (core/validate.py)."""

import numpy as np
import pytest

from bubsub.core.validate import check_int


def test_check_int_accepts_integers_in_range_and_returns_ints():
    assert check_int(np.int64(3), "n", 1) == 3 and type(check_int(np.int64(3), "n", 1)) is int
    assert check_int(0, "n") == 0
    assert check_int(16, "supersampling", 1, 16) == 16


@pytest.mark.parametrize("value, minimum, maximum, message", [
    (True, 1, None, "n must be a positive integer, got True"),  # a bool is never a count
    (2.0, 1, None, "n must be a positive integer, got 2.0"),
    (0, 1, None, "n must be a positive integer, got 0"),
    (-1, 0, None, "n must be a non-negative integer, got -1"),
    (17, 1, 16, r"n must be an integer in 1\.\.16, got 17"),
    (2, 3, None, "n must be an integer >= 3, got 2"),
])
def test_check_int_refuses_with_the_name_and_the_value(value, minimum, maximum, message):
    with pytest.raises(ValueError, match=message):
        check_int(value, "n", minimum, maximum)
