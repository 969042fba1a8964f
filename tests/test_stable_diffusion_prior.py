"""The Stable Diffusion prior adapter, offline: a tiny randomly initialised pipeline is built
and saved here (no network, no weights), loaded back through the adapter and checked."""

from __future__ import annotations

import json

import pytest
import torch

from l3d_app.errors import UserError


from l3d_app.diffusion.stable_diffusion import (StableDiffusionPrior, check_pipeline_folder,
                                                stable_diffusion_prior)
from l3d_app.losses import sds

MAX_LEN, HIDDEN, LATENT_SIDE, VAE_LEVELS = 16, 16, 8, 2   # image side = 8 * 2 ** (2 - 1) = 16
diffusers = transformers = None   # the modules, set by hf_modules below


@pytest.fixture(autouse=True, scope="module")
def hf_modules():
    """diffusers / transformers (in the test extra; a broken install fails here, it does not skip), imported
    when this file's tests run rather than when every worker collects (a 4 s import)."""
    global diffusers, transformers
    import diffusers as diffusers_module
    import transformers as transformers_module

    diffusers, transformers = diffusers_module, transformers_module


def _bytes_to_unicode() -> dict:
    """GPT-2/CLIP byte -> printable unicode table (the byte-level BPE alphabet)."""
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(0xA1, 0xAD)) + list(range(0xAE, 0x100))
    cs, n = bs[:], 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return dict(zip(bs, map(chr, cs)))


def _tiny_tokenizer(folder):
    """A CLIP tokenizer whose vocabulary is the byte alphabet (every prompt tokenises per character)."""
    chars = list(_bytes_to_unicode().values())
    vocab = {c: i for i, c in enumerate(chars + [c + "</w>" for c in chars] + ["<|startoftext|>", "<|endoftext|>"])}
    folder.mkdir()
    (folder / "vocab.json").write_text(json.dumps(vocab))
    (folder / "merges.txt").write_text("#version: 0.2\n")
    (folder / "tokenizer_config.json").write_text(json.dumps({"model_max_length": MAX_LEN}))
    return transformers.CLIPTokenizer.from_pretrained(str(folder), local_files_only=True), vocab


@pytest.fixture(scope="module")
def pipeline_dir(tmp_path_factory):
    """Folder of a saved tiny StableDiffusionPipeline (random weights, seeded)."""
    root = tmp_path_factory.mktemp("tiny_sd")
    tokenizer, vocab = _tiny_tokenizer(root / "tokenizer_src")
    torch.manual_seed(0)
    unet = diffusers.UNet2DConditionModel(
        sample_size=LATENT_SIDE, in_channels=4, out_channels=4, layers_per_block=1,
        block_out_channels=(8, 16), down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"),
        up_block_types=("CrossAttnUpBlock2D", "UpBlock2D"), cross_attention_dim=HIDDEN,
        norm_num_groups=4, attention_head_dim=2)
    vae = diffusers.AutoencoderKL(
        in_channels=3, out_channels=3, latent_channels=4, block_out_channels=(8, 16)[:VAE_LEVELS],
        down_block_types=("DownEncoderBlock2D",) * VAE_LEVELS, up_block_types=("UpDecoderBlock2D",) * VAE_LEVELS,
        norm_num_groups=4, sample_size=LATENT_SIDE * 2)
    text_encoder = transformers.CLIPTextModel(transformers.CLIPTextConfig(
        vocab_size=len(vocab), hidden_size=HIDDEN, intermediate_size=32, num_attention_heads=2,
        num_hidden_layers=2, max_position_embeddings=MAX_LEN, projection_dim=HIDDEN,
        bos_token_id=vocab["<|startoftext|>"], eos_token_id=vocab["<|endoftext|>"],
        pad_token_id=vocab["<|endoftext|>"]))
    scheduler = diffusers.DDPMScheduler(num_train_timesteps=1000, beta_schedule="scaled_linear",
                                        beta_start=0.00085, beta_end=0.012, clip_sample=False,
                                        steps_offset=1)
    pipe = diffusers.StableDiffusionPipeline(vae=vae, text_encoder=text_encoder, tokenizer=tokenizer, unet=unet,
                                             scheduler=scheduler, safety_checker=None, feature_extractor=None,
                                             requires_safety_checker=False)
    folder = root / "pipe"
    pipe.save_pretrained(str(folder))
    return folder


@pytest.fixture(scope="module")
def prior(pipeline_dir):
    return stable_diffusion_prior(str(pipeline_dir), device="cpu")


def test_loads_offline_frozen_fp32_on_cpu(prior, pipeline_dir):
    import os

    assert isinstance(prior, StableDiffusionPrior) and prior.is_latent
    assert os.environ.get("HF_HUB_OFFLINE") == "1"
    assert prior.dtype == torch.float32
    assert not any(p.requires_grad for p in prior.parameters())
    assert prior.latent_shape == (4, LATENT_SIDE, LATENT_SIDE) and prior.image_size == 16
    # alphas_cumprod: the scheduler's, float32, strictly decreasing in (0, 1)
    abar = prior.alphas_cumprod
    ref = diffusers.DDPMScheduler.from_pretrained(str(pipeline_dir), subfolder="scheduler").alphas_cumprod
    assert abar.dtype == torch.float32 and abar.shape == (1000,)
    assert torch.allclose(abar, ref.float()) and bool((abar[1:] < abar[:-1]).all())
    assert 0 < float(abar[-1]) and float(abar[0]) < 1


def test_prompt_embedding_shapes_and_uncond(prior):
    emb = prior.embed_prompt("a red cow")
    assert emb.cond.shape == (1, MAX_LEN, HIDDEN) and emb.uncond.shape == (1, MAX_LEN, HIDDEN)
    assert emb.cond.dtype == torch.float32 and torch.isfinite(emb.cond).all()
    assert not torch.allclose(emb.cond, emb.uncond)
    assert torch.equal(prior.embed_prompt("").cond, emb.uncond)      # uncond = the empty prompt
    assert torch.equal(prior.embed_prompt("a red cow").cond, emb.cond)   # deterministic


def test_encode_decode_shapes_and_range(prior):
    g = torch.Generator().manual_seed(0)
    images = torch.rand(2, 3, 16, 16, generator=g)
    z = prior.encode(images)
    assert z.shape == (2, 4, LATENT_SIDE, LATENT_SIDE) and z.dtype == torch.float32
    assert torch.isfinite(z).all()
    out = prior.decode(z)
    assert out.shape == (2, 3, 16, 16) and out.dtype == torch.float32
    assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0
    # the scaling factor is applied: encode = scaling_factor * posterior mean
    mean = prior.vae.encode(images * 2 - 1).latent_dist.mean
    assert torch.allclose(z, mean * prior.scaling_factor, atol=1e-6)


def test_noise_prediction_shape(prior):
    emb = prior.embed_prompt("a blue cube")
    x_t = torch.randn(3, 4, LATENT_SIDE, LATENT_SIDE, generator=torch.Generator().manual_seed(1))
    t = torch.tensor([0, 500, 999])
    eps = prior.predict_noise(x_t, t, emb.cond.expand(3, -1, -1))
    assert eps.shape == x_t.shape and eps.dtype == torch.float32 and torch.isfinite(eps).all()


def test_one_sds_step_gives_finite_latent_and_image_gradients(prior):
    emb = prior.embed_prompt("a red cow")
    g = torch.Generator().manual_seed(2)
    latent = torch.randn(2, *prior.latent_shape, generator=g).requires_grad_(True)
    out = sds.sds_loss(prior, latent, emb, guidance_scale=100.0, generator=g)
    out.loss.backward()
    assert out.finite and torch.isfinite(latent.grad).all() and float(latent.grad.abs().sum()) > 0
    # the gradient w.r.t. the latent is exactly the SDS gradient w(t) (eps_hat - eps)
    assert torch.allclose(latent.grad, out.grad, atol=1e-5)
    # and through the VAE encoder, from rendered RGB pixels
    image = torch.rand(1, 3, 16, 16, generator=g).requires_grad_(True)
    out = sds.sds_loss(prior, sds.rgb_to_model_space(prior, image), emb, guidance_scale=100.0, generator=g)
    out.loss.backward()
    assert torch.isfinite(image.grad).all() and float(image.grad.abs().sum()) > 0


def test_clear_errors_for_bad_paths(tmp_path, pipeline_dir):
    with pytest.raises(UserError, match="prior.path"):
        check_pipeline_folder(None)
    with pytest.raises(UserError, match="does not exist"):
        stable_diffusion_prior(str(tmp_path / "nowhere"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="model_index.json"):
        stable_diffusion_prior(str(tmp_path / "empty"))
    with pytest.raises(UserError, match="dtype"):
        stable_diffusion_prior(str(pipeline_dir), dtype="int8")


def test_missing_diffusers_is_a_user_error(monkeypatch, pipeline_dir):
    import builtins

    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name == "diffusers" or name.startswith("diffusers."):
            raise ImportError("No module named 'diffusers'", name="diffusers")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    with pytest.raises(UserError, match="diffusers"):
        stable_diffusion_prior(str(pipeline_dir))


def test_sds_nerf_runs_on_the_tiny_pipeline_with_view_prompts_and_latent_steps(pipeline_dir, compose, tmp_path):
    from l3d_app.app import run_task

    cfg = compose("task=sds_nerf", "prior=stable_diffusion", f"prior.path={pipeline_dir}", "iters=2",
                  "latent_iter_ratio=0.5", "eval_every=2", "eval_views=1", "num_frames=2", "n_samples=8",
                  "image_size=8", "turntable_size=8", "guidance_scale=100", "tensorboard=false", "threads=1", "device=cpu",
                  "prompt=a hamburger")
    run_task(cfg, out_dir=tmp_path)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["iters"] == 2 and m["latent_iters"] == 1 and m["skipped_steps"] == 0
    assert m["view_prompts"]["back"] == "a hamburger, back view"     # on for Stable Diffusion
    assert m["match_rate"] is None                  # free text: the built-in checker has no verdict
    assert (tmp_path / "sds_nerf.gif").exists()


def test_missing_path_is_reported_before_loading(compose):
    from l3d_app.app import run_task

    with pytest.raises(UserError, match="prior.path"):
        run_task(compose("task=sds_mesh", "prior=stable_diffusion"), out_dir=None)
