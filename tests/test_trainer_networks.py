"""Depth networks: shapes, bounded depth head, gradients, ONNX Runtime equivalence."""

import numpy as np
import pytest
import torch

from collect.errors import InputError
from trainer.networks import ARCHITECTURES, build_network
from trainer.networks.depth_head import BoundedInverseDepth
from trainer.onnx_export import export_onnx
from trainer.training_defaults import ARCH_NAMES, DEFAULT_ARCH, DEFAULT_WIDTHS
from trainer.inference import ort_session


def test_depth_head_formula_and_bounds():
    head = BoundedInverseDepth(0.04, 0.12)
    logits = torch.tensor([-50.0, 0.0, 50.0])
    depth = head(logits)
    assert depth[0] == pytest.approx(0.12, rel=1e-4)  # sigmoid -> 0: 1/max
    assert depth[1] == pytest.approx(1.0 / (1 / 0.12 + (1 / 0.04 - 1 / 0.12) * 0.5))
    assert depth[2] == pytest.approx(0.04, rel=1e-4)
    assert float(head(torch.tensor(head.logit(0.093)))) == pytest.approx(0.093)


def test_the_command_line_offers_every_network_with_a_default_width():
    # the options come from the torch-free trainer.training_defaults, the classes from trainer.networks
    assert ARCH_NAMES == tuple(ARCHITECTURES)
    assert DEFAULT_ARCH in ARCH_NAMES and set(DEFAULT_WIDTHS) == set(ARCH_NAMES)


@pytest.mark.parametrize("arch", sorted(ARCHITECTURES))
def test_network_output_shape_range_and_gradient(arch):
    torch.manual_seed(0)
    net = build_network(arch, 0.125, 0.04, 0.12)
    x = torch.randn(2, 1, 64, 96)
    depth = net(x)
    assert depth.shape == (2, 1, 64, 96)
    assert float(depth.detach().min()) > 0.04 and float(depth.detach().max()) < 0.12
    depth.mean().backward()
    grads = [p.grad for p in net.parameters() if p.requires_grad]
    assert all(g is not None for g in grads)
    assert any(float(g.abs().sum()) > 0 for g in grads[:3])  # reaches the first layers


@pytest.mark.parametrize("arch", sorted(ARCHITECTURES))
def test_onnx_runtime_matches_torch(arch, tmp_path):
    torch.manual_seed(1)
    net = build_network(arch, 0.125, 0.04, 0.12).eval()
    path = export_onnx(net, (64, 64), tmp_path / "m.onnx")
    x = np.random.default_rng(0).standard_normal((2, 1, 64, 64)).astype(np.float32)
    with torch.inference_mode():
        ref = net(torch.from_numpy(x)).numpy()
    out = ort_session(path).run(None, {"ir": x})[0]
    assert out.shape == ref.shape
    assert np.max(np.abs(out - ref)) < 1e-4


def test_unknown_arch_and_bad_width_are_input_errors():
    with pytest.raises(InputError):
        build_network("vgg", 1.0, 0.04, 0.12)
    with pytest.raises(InputError):
        build_network("resnet", 0.0, 0.04, 0.12)


@pytest.mark.parametrize("arch", sorted(ARCHITECTURES))
@pytest.mark.parametrize("width", [0.3, 0.6, 1.3])
def test_every_width_the_command_line_accepts_builds(arch, width):
    """Was: packnet at width 0.3, 0.4, 0.6 or 0.8 failed in torch's GroupNorm (76 channels are not
    16 groups), a traceback from bubble train --arch packnet --width 0.3."""
    net = build_network(arch, width, 0.04, 0.12).eval()
    with torch.inference_mode():
        assert net(torch.zeros(1, 1, 64, 64)).shape == (1, 1, 64, 64)


def test_depth_head_output_stays_within_its_float32_bounds():
    """Was: 0.12000000476 for a saturated logit, one float32 step above max_depth, under a docstring
    that said 'strictly inside (min_depth, max_depth)'."""
    head = BoundedInverseDepth(0.04, 0.12)
    depth = head(torch.tensor([-1e4, -50.0, -17.0, 0.0, 17.0, 50.0, 1e4]))
    assert float(depth.max()) <= float(np.float32(0.12)) and float(depth.min()) >= float(np.float32(0.04))
    assert depth[0] == np.float32(0.12) and depth[-1] == np.float32(0.04)  # a saturated logit gives the bound
