"""NormalResNet: shapes, range, layer sizes of the paper network, validation, overfitting."""

import pytest
import torch

from sss2bathy.losses import NormalLoss
from sss2bathy.models.normal_cnn import ChannelNorm, NormalResNet, channel_norm_copy


def test_output_shape_dtype_and_range():
    torch.manual_seed(0)
    net = NormalResNet(base_width=4, n_blocks=2)
    x = 10 * torch.randn(3, 1, 16, 40)  # large inputs: tanh must still bound the output
    y = net(x)
    assert y.shape == (3, 1, 16, 40) and y.dtype == torch.float32
    assert y.abs().max() <= 1.0 and y.std() > 0


def test_paper_network_layer_sizes_and_parameter_count():
    net = NormalResNet()  # base_width 64, 7 blocks, 7x7 outer kernels
    convs = [m for m in net.modules() if isinstance(m, torch.nn.Conv2d | torch.nn.ConvTranspose2d)]
    assert tuple(convs[0].weight.shape) == (64, 1, 7, 7)
    assert tuple(convs[2].weight.shape) == (256, 128, 3, 3)  # second stride-2 conv
    assert convs[1].stride == convs[2].stride == (2, 2)
    assert tuple(convs[-1].weight.shape) == (1, 64, 7, 7)
    assert sum(isinstance(m, torch.nn.InstanceNorm2d) for m in net.modules()) == 3 + 2 * 7 + 2
    expected = (
        (1 * 64 * 49 + 64)
        + (64 * 128 * 9 + 128)
        + (128 * 256 * 9 + 256)
        + 7 * 2 * (256 * 256 * 9 + 256)
        + (256 * 128 * 9 + 128)
        + (128 * 64 * 9 + 64)
        + (64 * 49 + 1)
    )
    assert sum(p.numel() for p in net.parameters()) == expected


@pytest.mark.parametrize(
    "shape, axis", [((1, 1, 18, 32), "H"), ((1, 1, 16, 30), "W"), ((1, 1, 4, 32), "H")]
)
def test_rejects_sizes_not_divisible_by_four(shape, axis):
    net = NormalResNet(base_width=2, n_blocks=1)
    with pytest.raises(ValueError, match=f"{axis}="):
        net(torch.zeros(shape))


def test_rejects_wrong_channels_and_bad_arguments():
    with pytest.raises(ValueError, match=r"\[B, 1, H, W\]"):
        NormalResNet(base_width=2, n_blocks=1)(torch.zeros(1, 2, 16, 16))
    with pytest.raises(ValueError, match="outer_kernel"):
        NormalResNet(outer_kernel=6)
    with pytest.raises(ValueError, match="base_width"):
        NormalResNet(base_width=0)


def test_config_rebuilds_an_identical_network():
    net = NormalResNet(base_width=3, n_blocks=2, use_dropout=True)
    cfg = net.config()
    assert cfg["_target_"] == "sss2bathy.models.normal_cnn.NormalResNet"
    twin = NormalResNet(**{k: v for k, v in cfg.items() if k != "_target_"})
    twin.load_state_dict(net.state_dict(), strict=True)
    x = torch.randn(2, 1, 8, 16)
    net.eval(), twin.eval()
    torch.testing.assert_close(net(x), twin(x))


def test_tiny_network_overfits_one_window():
    torch.manual_seed(0)
    net = NormalResNet(base_width=8, n_blocks=2)
    x = torch.randn(1, 1, 16, 32)
    bins, pings = torch.linspace(-1, 1, 32), torch.linspace(0, 3, 16)
    target = 0.3 * torch.sin(3 * bins)[None, None, None, :] * torch.cos(pings)[None, None, :, None]
    mask = torch.rand(1, 1, 16, 32) > 0.2
    loss_fn = NormalLoss("normal_aware")
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(40):
        loss = loss_fn(net(x), target, mask)["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] / 10


def test_channel_norm_is_instance_norm_in_either_memory_format():
    x = torch.randn(3, 5, 8, 12) * 4 + 1
    ref = torch.nn.InstanceNorm2d(5, affine=False, track_running_stats=False)(x)
    norm = ChannelNorm(1e-5)
    torch.testing.assert_close(norm(x), ref, atol=1e-5, rtol=1e-5)
    cl = norm(x.contiguous(memory_format=torch.channels_last))
    assert cl.is_contiguous(memory_format=torch.channels_last)  # read as it is, no copy back
    torch.testing.assert_close(cl, ref, atol=1e-5, rtol=1e-5)


def test_channel_norm_copy_replaces_plain_instance_norms_only():
    torch.manual_seed(0)
    net = NormalResNet(base_width=4, n_blocks=1).eval()
    extra = torch.nn.Sequential(net, torch.nn.InstanceNorm2d(1, affine=True))
    copy = channel_norm_copy(extra)
    n_plain = sum(isinstance(m, torch.nn.InstanceNorm2d) and not m.affine for m in extra.modules())
    assert n_plain > 0 and sum(isinstance(m, ChannelNorm) for m in copy.modules()) == n_plain
    kept = [m for m in copy.modules() if isinstance(m, torch.nn.InstanceNorm2d)]
    assert len(kept) == 1 and kept[0].affine  # an affine one is not the same function
    assert any(isinstance(m, torch.nn.InstanceNorm2d) for m in net.modules())  # net unchanged
    x = torch.randn(2, 1, 16, 32)
    with torch.inference_mode():
        torch.testing.assert_close(copy[0](x), net(x), atol=1e-5, rtol=1e-5)
