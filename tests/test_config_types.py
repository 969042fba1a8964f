"""Command-line values against the type of the default they replace, and config lists of numbers."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from l3d_app.errors import UserError
from l3d_app.runtime.config_values import config_floats
from l3d_app.command_line import override_type_errors, value_override_keys, value_type_error


@pytest.mark.parametrize("default, value, message", [
    (4500, 2.5, "iters must be an integer, got 2.5"),
    (4500, True, "iters must be an integer, got true"),
    (4500, "many", "iters must be an integer, got 'many'"),
    (0.5, "abc", "iters must be a number, got 'abc'"),
    (0.5, False, "iters must be a number, got false"),
    (False, "no", "iters must be true or false, got 'no'"),
    (False, 0, "iters must be true or false, got 0"),
])
def test_a_value_of_the_wrong_type_is_named(default, value, message):
    assert value_type_error("iters", default, value) == message


@pytest.mark.parametrize("default, value", [
    (4500, 10), (4500, 1e3), (4500, None),          # an integral float is an integer (1e3 is how some write 1000)
    (0.5, 2), (0.5, 1e-3), (0.5, float("inf")),
    (True, False),
    ("auto", True), ("auto", 3), (None, "anything"), (["a", "b"], "x"),   # strings, string lists, null: the task checks
])
def test_a_value_that_fits_passes(default, value):
    assert value_type_error("k", default, value) is None


def test_override_type_errors_reads_nested_keys_and_skips_unknown_ones():
    defaults = OmegaConf.create({"iters": 10, "strategy": {"max_gaussians": 100, "grow": 0.1}, "name": "a"})
    cfg = OmegaConf.create({"iters": 10.0, "strategy": {"max_gaussians": 1.5, "grow": "x"}, "name": 3, "extra": 1})
    assert override_type_errors(cfg, defaults, ["iters", "strategy.max_gaussians", "strategy.grow", "name", "extra"]) == [
        "strategy.max_gaussians must be an integer, got 1.5", "strategy.grow must be a number, got 'x'"]


def test_value_override_keys_leaves_out_groups_additions_and_deletions():
    overrides = ["task=gs_train", "renderer@point_renderer=points", "iters=3", "data.root=x", "+new=1", "~old"]
    assert value_override_keys(overrides, ["task", "data", "renderer@point_renderer"]) == ["iters", "data.root"]


def test_config_floats():
    assert config_floats(OmegaConf.create({"v": [1, 2.5, -3]}).v, "v", 3) == [1.0, 2.5, -3.0]
    assert config_floats((0, 1), "r") == [0.0, 1.0]
    for bad, length, needle in [([1, 2], 3, "v must be a list of 3 numbers, got \\[1, 2\\]"),
                                ([1, "a"], None, "v must be a list of numbers, got \\[1, 'a'\\]"),
                                ([1, True], None, "list of numbers"), (5, None, "got 5"), (None, 2, "got None")]:
        with pytest.raises(UserError, match=needle):
            config_floats(bad, "v", length)


def test_a_list_of_numbers_takes_numbers_of_any_length():
    assert value_type_error("background", [1.0, 1.0, 1.0], [0, 0.5]) is None           # the task checks the length
    assert value_type_error("sweep", [1, 2], []) is None
    assert value_type_error("formats", ["gif", "png"], [1]) is None                    # not a number list: the task's
    assert value_type_error("background", [1.0, 1.0, 1.0], 1) == "background must be a list of numbers, got 1"
    assert value_type_error("background", [1.0, 1.0, 1.0], [1, "white", 1]) == (
        "background must be a list of numbers, got [1, 'white', 1]")
    defaults = OmegaConf.create({"background": [1.0, 1.0, 1.0]})
    assert override_type_errors(OmegaConf.create({"background": [1, True, 0]}), defaults, ["background"]) == [
        "background must be a list of numbers, got [1, True, 0]"]
