"""tasks/common.py's config checks: a bad number is a UserError that names its key (one line,
exit 2 at the command line); good values pass."""

import pytest
from omegaconf import OmegaConf

from l3d_app.errors import UserError
from l3d_app.tasks.common import require_nonnegative, require_positive


@pytest.mark.parametrize("value", [-1, -0.5, "x", True, None])
def test_nonnegative_rejects_and_names_the_key(value):
    cfg = OmegaConf.create({"w_free": 0.1, "free_softness": value})
    with pytest.raises(UserError, match="free_softness must be a number >= 0"):
        require_nonnegative(cfg, "w_free", "free_softness")


def test_nonnegative_accepts_zero_and_positive_and_positive_rejects_zero():
    cfg = OmegaConf.create({"w_free": 0, "free_softness": 0.01})
    require_nonnegative(cfg, "w_free", "free_softness")
    with pytest.raises(UserError, match="w_free must be a positive number"):
        require_positive(cfg, "w_free")
