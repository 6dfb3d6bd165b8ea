"""The shared option validators: each names the option and what it must be, accepts what it
must and refuses a Python bool as a number."""
import numpy as np
import pytest

from jaxrkpm.base.checks import count, flag, positive


@pytest.mark.parametrize("v", [1, 2.5, np.float32(1e-3), np.int64(3)])
def test_positive_accepts_finite_positive_numbers(v):
    positive("rtol", v)


@pytest.mark.parametrize("v", [0, -1.0, np.inf, np.nan, True, "1", None])
def test_positive_refuses_the_rest(v):
    with pytest.raises(ValueError, match="rtol must be a positive number"):
        positive("rtol", v)


def test_count_holds_its_lower_bound():
    count("steps", 0)
    count("steps", np.int32(4), 1)
    for v, low in [(0, 1), (-1, 0), (2.0, 0), (True, 0)]:
        with pytest.raises(ValueError, match=f"steps must be an int >= {low}"):
            count("steps", v, low)


def test_flag_takes_only_booleans():
    flag("same", True)
    flag("same", np.bool_(False))
    for v in (0, 1, "False", None):
        with pytest.raises(ValueError, match="same must be True or False"):
            flag("same", v)
