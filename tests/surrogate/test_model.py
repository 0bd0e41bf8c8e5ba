"""The architecture is the paper's (section 2.3, Fig. 4), and it can fit a tiny batch."""

import numpy as np
import torch
from torch import nn

from calendaring.data.dataset import synthetic_dataset
from surrogate.data import Normalisation, SurrogateDataset
from surrogate.losses import SurrogateLoss
from surrogate.model import DualBranchMLP, ModelConfig, ResidualBlock


def _linears(module):
    return [(m.in_features, m.out_features) for m in module.modules() if isinstance(m, nn.Linear)]


def test_layer_sizes_are_the_papers():
    m = DualBranchMLP()
    # shared extractor: 8 -> 256, block 256 -> 128 (fc + skip projection), block 128 -> 64
    assert _linears(m.features) == [(8, 256), (256, 128), (256, 128), (128, 64), (128, 64)]
    assert _linears(m.pressure_head) == [(64, 128), (128, 196)]
    assert _linears(m.dist_head) == [(64, 256), (256, 512), (512, 900)]
    blocks = [b for b in m.features if isinstance(b, ResidualBlock)]
    assert [b.norm.normalized_shape for b in blocks] == [(128,), (64,)]
    assert all(isinstance(b.skip, nn.Linear) for b in blocks)
    slopes = {a.negative_slope for a in m.features.modules() if isinstance(a, nn.LeakyReLU)}
    assert slopes == {0.1}
    drops = [d.p for d in m.modules() if isinstance(d, nn.Dropout)]
    assert drops == [0.3] * 6  # embed, 2 blocks, pressure head, 2 in the distribution head
    assert isinstance(m.pressure_head[-1], nn.Softplus)
    assert sum(isinstance(a, nn.ReLU) for a in m.pressure_head) == 1
    assert sum(isinstance(a, nn.ReLU) for a in m.dist_head) == 2


def test_identity_skip_when_widths_match():
    b = ResidualBlock(16, 16, 0.0, 0.1)
    assert isinstance(b.skip, nn.Identity)


def test_output_shapes_softmax_and_softplus():
    torch.manual_seed(0)
    m = DualBranchMLP().eval()
    with torch.no_grad():
        m.pressure_head[-2].bias.fill_(-40.0)  # pre-activations far below zero
        p, d = m(torch.rand(7, 8))
    assert p.shape == (7, 196) and d.shape == (7, 30, 30)
    assert torch.all(p > 0)
    np.testing.assert_allclose(d.sum(dim=(1, 2)).numpy(), 1.0, rtol=1e-5)
    assert torch.all(d >= 0)


def test_overfits_a_tiny_batch():
    torch.manual_seed(0)
    ds = synthetic_dataset(4, seed=3)
    data = SurrogateDataset(ds, Normalisation.fit(ds.pressure))
    u, p, d, w = data.tensors()
    m = DualBranchMLP(ModelConfig(dropout=0.0))
    opt = torch.optim.Adam(m.parameters(), lr=1e-3)
    loss = SurrogateLoss()
    first = None
    for _ in range(250):
        opt.zero_grad()
        terms = loss(*_pair(m(u), p, d), w)
        terms.total.backward()
        opt.step()
        first = first if first is not None else float(terms.total.detach())
    m.eval()
    with torch.no_grad():
        final = loss(*_pair(m(u), p, d), w)
    assert float(final.mse) < 1e-4
    assert float(final.kl) < 1e-3
    assert float(final.total) < 1e-3 * first


def _pair(out, p, d):
    return out[0], p, out[1], d
