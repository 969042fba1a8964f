import pytest

from l3d_app.errors import UserError
from l3d_app.registry import Registry


def make_registry():
    reg = Registry("widget")

    @reg.register("box")
    class Box:
        def __init__(self, size: float = 1.0, color: str = "red"):
            self.size, self.color = size, color

    @reg.register("free")
    def free(**kwargs):
        return kwargs

    return reg


def test_build_passes_keys_as_keywords():
    box = make_registry().build({"name": "box", "size": 2.5})
    assert (box.size, box.color) == (2.5, "red")


def test_unknown_name_lists_known_names_and_suggests():
    with pytest.raises(UserError) as err:
        make_registry().build({"name": "bx"})
    msg = str(err.value)
    assert "unknown widget 'bx'" in msg and "box, free" in msg and "Did you mean 'box'" in msg


def test_unknown_key_is_rejected_with_known_keys():
    with pytest.raises(UserError) as err:
        make_registry().build({"name": "box", "sise": 2})
    msg = str(err.value)
    assert "unknown key 'sise'" in msg and "color, size" in msg and "'size'" in msg


def test_var_keyword_entries_accept_anything():
    assert make_registry().build({"name": "free", "anything": 1}) == {"anything": 1}


def test_missing_name_and_double_registration():
    reg = make_registry()
    with pytest.raises(UserError):
        reg.build({"size": 1})
    with pytest.raises(KeyError):
        reg.register("box")(lambda: None)


def test_omegaconf_values_become_plain_python():
    from omegaconf import OmegaConf

    box = make_registry().build(OmegaConf.create({"name": "box", "size": [1, 2]}))
    assert box.size == [1, 2] and type(box.size) is list
