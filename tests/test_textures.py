import torch

from l3d_app.geometry.textures import sample_texture, sample_texture_indexed


def test_grid_sample_and_gather_paths_agree_inside_and_outside_the_unit_square():
    gen = torch.Generator().manual_seed(0)
    texture = torch.rand(5, 7, 3, generator=gen, dtype=torch.float64)
    uv = torch.rand(200, 2, generator=gen, dtype=torch.float64) * 1.4 - 0.2
    torch.testing.assert_close(sample_texture(texture, uv), sample_texture_indexed(texture, uv))


def test_texel_centres_and_v_up():
    texture = torch.arange(6, dtype=torch.float64).reshape(2, 3, 1)  # rows top to bottom
    # centre of the top-left texel: u = 0.5/3, v = 1 - 0.5/2 (v up)
    uv = torch.tensor([[0.5 / 3, 0.75], [2.5 / 3, 0.25]], dtype=torch.float64)
    assert sample_texture(texture, uv).flatten().tolist() == [0.0, 5.0]
    assert sample_texture_indexed(texture, uv).flatten().tolist() == [0.0, 5.0]


def test_indexed_picks_texture_per_point():
    textures = torch.stack([torch.zeros(2, 2, 3), torch.ones(2, 2, 3)])
    uv = torch.full((4, 2), 0.5)
    out = sample_texture_indexed(textures, uv, torch.tensor([0, 1, 1, 0]))
    assert out[:, 0].tolist() == [0.0, 1.0, 1.0, 0.0]
