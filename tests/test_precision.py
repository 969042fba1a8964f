"""runtime/precision.py: autocast from a precision string, and maybe_compile's fallback."""

import warnings

import pytest
import torch

from l3d_app.runtime import precision as prec
from l3d_app.runtime.precision import PRECISIONS, autocast, check_precision, maybe_compile


def _linear():
    torch.manual_seed(0)
    return torch.nn.Linear(8, 4), torch.randn(5, 8)


def test_fp32_is_a_no_op():
    lin, x = _linear()
    with autocast("fp32", "cpu"):
        assert not torch.is_autocast_enabled("cpu")
        y = lin(x)
    assert y.dtype == torch.float32
    torch.testing.assert_close(y, x @ lin.weight.T + lin.bias, rtol=0, atol=0)


@pytest.mark.parametrize("device", ["cpu", torch.device("cpu"), None])
def test_bf16_autocasts_linear_on_cpu_and_keeps_fp32_parameters(device):
    lin, x = _linear()
    with autocast("bf16", device):
        assert torch.is_autocast_enabled("cpu")
        assert torch.get_autocast_dtype("cpu") == torch.bfloat16
        y = lin(x)
    assert not torch.is_autocast_enabled("cpu")          # restored on exit
    assert y.dtype == torch.bfloat16
    ref = x.double() @ lin.weight.double().T + lin.bias.double()
    # bf16 has an 8-bit mantissa: relative error ~ 2^-8 per rounding
    assert (y.double() - ref).abs().max() <= 2e-2 * ref.abs().max()
    y.float().sum().backward()
    assert lin.weight.grad.dtype == torch.float32 and torch.isfinite(lin.weight.grad).all()
    torch.testing.assert_close(lin.weight.grad, x.sum(0).expand(4, 8), rtol=2e-2, atol=2e-2)


@pytest.mark.parametrize("bad", ["fp16", "FP32", "float32", "", "bfloat16"])
def test_unknown_precision_is_a_value_error_naming_the_allowed_ones(bad):
    with pytest.raises(ValueError) as err:
        autocast(bad, "cpu")
    for name in PRECISIONS:
        assert name in str(err.value)
    with pytest.raises(ValueError):
        check_precision(bad)
    assert check_precision("bf16") == "bf16"


def test_maybe_compile_disabled_returns_the_object_itself():
    lin, _ = _linear()
    assert maybe_compile(lin, enabled=False) is lin


def test_maybe_compile_without_torch_compile_warns_and_runs_eagerly(monkeypatch):
    monkeypatch.setattr(prec, "compile_available", lambda: False)
    lin, x = _linear()
    with pytest.warns(RuntimeWarning, match="not available"):
        f = maybe_compile(lin, enabled=True)
    assert f is lin


def test_maybe_compile_falls_back_when_compilation_fails(monkeypatch):
    """A compiler that raises at the first call (as inductor does without a C++ toolchain):
    the wrapper warns once, returns the eager result and forwards attributes to the module."""
    calls = []

    def broken_compile(fn, **kw):
        calls.append(kw)

        def compiled(*a, **k):
            raise RuntimeError("no C++ compiler\nmore lines")
        return compiled

    monkeypatch.setattr(prec, "compile_available", lambda: True)
    monkeypatch.setattr(torch, "compile", broken_compile)
    lin, x = _linear()
    f = maybe_compile(lin, enabled=True, mode="max-autotune-no-cudagraphs")
    assert calls == [{"mode": "max-autotune-no-cudagraphs"}]
    with pytest.warns(RuntimeWarning, match="no C\\+\\+ compiler"):
        y = f(x)
    torch.testing.assert_close(y, lin(x), rtol=0, atol=0)
    assert f.failed and f.weight is lin.weight
    with warnings.catch_warnings():
        warnings.simplefilter("error")                   # once only
        torch.testing.assert_close(f(x), lin(x), rtol=0, atol=0)


def test_maybe_compile_bad_kwargs_fall_back_at_once(monkeypatch):
    monkeypatch.setattr(prec, "compile_available", lambda: True)

    def raising(fn, **kw):
        raise RuntimeError("Unrecognized mode")
    monkeypatch.setattr(torch, "compile", raising)
    lin, _ = _linear()
    with pytest.warns(RuntimeWarning, match="Unrecognized mode"):
        assert maybe_compile(lin, enabled=True, mode="nonsense") is lin


def test_maybe_compile_reraises_errors_after_a_successful_call(monkeypatch):
    """Once the compiled function has run, a later exception is the function's own: not hidden."""
    monkeypatch.setattr(prec, "compile_available", lambda: True)
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: fn)     # 'compiles' to itself

    def f(x):
        if x < 0:
            raise ValueError("negative")
        return x * 2
    g = maybe_compile(f, enabled=True)
    assert g(2) == 4
    with pytest.raises(ValueError, match="negative"):
        g(-1)


def test_compile_available_matches_this_torch():
    assert prec.compile_available() == hasattr(torch, "compile")
