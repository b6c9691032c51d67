"""What a step computes with fewer operations gives what it gave: the index sets worked out in numpy,
the motion evaluated once for the data and TV frames, the RS rows in one pass over the first
evaluation's frames, both axes' warp and interpolation matrices built at once, the decoder as one
autograd function, constant interpolation matrices built in numpy."""

import numpy as np
import pytest
import torch
from test_stfm import scene_problem, small_settings
from torch import nn

from rngcam.recon.methods import selfcal
from rngcam.recon.methods.stfm import make_stfm
from rngcam.recon.methods.stfm.decoder import decode
from rngcam.recon.methods.stfm.fields import _build_interp_matrix, _stacked_interp, translate_image
from rngcam.recon.methods.stfm.grid import sorted_sample


@pytest.fixture(scope="module")
def sineball16():
    return scene_problem("sineball", 16)


def test_sampled_index_sets_are_the_tensor_formulas():
    """Rows, TV frames and GS windows drawn as the step drew them with tensor operations, from the
    same generator: the same indices, and the generator left in the same state."""
    fitted = torch.tensor([0, 2, 3, 5, 8, 9, 11])
    for seed in range(5):
        a, b = torch.Generator().manual_seed(seed), torch.Generator().manual_seed(seed)
        assert torch.equal(torch.from_numpy(sorted_sample(40, 6, a)),
                           torch.randperm(40, generator=b)[:6].sort().values)
        start = int(torch.randint(7, (1,), generator=b))
        assert int(torch.randint(7, (1,), generator=a)) == start
        assert torch.equal(torch.from_numpy(fitted.numpy()[(start + np.arange(5)) % 7]),
                           fitted[(start + torch.arange(5)) % 7])
        assert torch.equal(torch.rand(3, generator=a), torch.rand(3, generator=b))


def test_window_and_row_frames_are_the_tensor_formulas(sineball16):
    m = make_stfm(sineball16, small_settings(gs_windows_per_step=1))
    loss, grid = m.loss, m.grid
    for window in range(grid.w_gs.shape[0]):
        windows = torch.tensor([window])
        _, frames, host = loss._step_windows(windows)
        expected = torch.nonzero(grid.w_gs_host[windows].sum(0) > 0).flatten()
        assert torch.equal(frames, expected) and np.array_equal(host, expected.numpy())
        for rows in (torch.arange(0, 4), torch.arange(6, 13), torch.tensor([15, 0, 1])):
            shared, rest = loss._split_rs_frames(rows.numpy(), None, host)
            touched = grid.rs_frames(rows)
            inside = torch.isin(touched, expected)
            assert np.array_equal(shared, touched[inside].numpy()) and np.array_equal(rest, touched[~inside].numpy())


def test_tv_from_the_shared_motion_evaluation_is_the_tv_alone(sineball16):
    m = make_stfm(sineball16, small_settings(init="random"))
    with torch.no_grad():  # a motion that is not zero
        for p in m.model.fields["motion"].parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(1)))
    idx, first = torch.tensor([3, 7, 15]), np.array([0, 1, 2, 9])
    alone = m.loss.tv_term(idx).detach()
    frames, u_tv = m.loss._first_frames(first, idx, None if not m.parts.static else m.model.static())
    assert float(alone) > 0
    assert float(m.loss.tv_term(idx, u_tv)) == pytest.approx(float(alone), rel=1e-6)
    assert torch.allclose(frames, m.model.frames(torch.from_numpy(first)), atol=1e-6)


@pytest.mark.parametrize("anchor,geometry", [("soft", "off"), ("hard", "off"), ("soft", "shift")])
def test_rs_term_in_one_pass_is_the_rows_of_every_frame(sineball16, anchor, geometry):
    """The RS term from the first evaluation's frames (shared with the GS windows, anchored where the
    anchoring is hard, moved by a learned shift, and the rest) equals the rows computed from every
    frame they see."""
    m = make_stfm(sineball16, small_settings(init="random", gs_anchor=anchor, gs_windows_per_step=1,
                                             frame_chunk=64, learn_geometry=geometry))
    assert m.learned_pose.learned == (geometry == "shift")
    if m.learned_pose.learned:  # a learned shift: the RS term sees the frames moved
        with torch.no_grad():
            m.learned_pose.parameter[:2] = torch.tensor([0.3, -0.6])
    for rows, window in ((torch.arange(0, 5), 0), (torch.arange(5, 12), 1), (torch.arange(11, 16), 2)):
        terms = m.loss.loss_terms(rows, None, gs_windows=torch.tensor([window]))
        with torch.no_grad():
            pred = m.loss.rs_apply(lambda idx: m.model.pose.rs_view(m.model.video_frames(idx, native=True)), rows)
        expected = m.loss.rs_scale(len(rows)) * float(m.loss.rs_miss(pred, rows).square().sum())
        assert expected > 0 and terms["rs"] == pytest.approx(expected, rel=1e-5)


@pytest.mark.parametrize("size", [12, 16])
def test_square_warp_by_a_shift_is_the_bicubic_warp(size):
    """Both axes' bicubic shift matrices built at once (a square image) give grid_sample's warp and its gradients."""
    images = torch.rand(2, 3, size, size, dtype=torch.float64, generator=torch.Generator().manual_seed(3))

    def both(path, shift):
        x, d = images.clone().requires_grad_(), torch.tensor(shift, dtype=torch.float64, requires_grad=True)
        out = path(x, d)
        weights = torch.linspace(-1, 1, out.numel(), dtype=torch.float64).view_as(out)
        return out.detach(), torch.autograd.grad((out * weights).sum(), [x, d])

    def by_matrix(x, d):
        m = torch.eye(3, dtype=x.dtype)
        m = torch.cat([torch.cat([m[:2, :2], d[:, None]], dim=1), m[2:]])
        return selfcal.warp(x, m)

    for shift in ([0.0, 0.0], [0.37, -0.81], [-2.6, 1.25], [3.0, -1.0]):
        fast, fast_grads = both(selfcal.warp_translate, shift)
        slow, slow_grads = both(by_matrix, shift)
        assert torch.allclose(fast, slow, atol=1e-10)
        for a, b in zip(fast_grads, slow_grads, strict=True):
            assert torch.allclose(a, b, atol=1e-8)


def test_square_translate_image_is_the_per_axis_matrices():
    """translate_image on a square grid (both axes' interpolation weights at once, from comparisons with
    the knots) against the matrices built per axis, values and gradients, whole-knot moves included
    (where the weights' slope is one-sided)."""
    gen = torch.Generator().manual_seed(0)
    image = torch.rand(9, 9, 2, dtype=torch.float64, generator=gen).requires_grad_()
    axis = torch.linspace(-1, 1, 5, dtype=torch.float64)
    shifts = torch.tensor([[0.0, 0.0], [0.25, -0.5], [0.13, -0.41], [-0.9, 1.3]], dtype=torch.float64)

    def reference(img, s):
        n = len(s)
        m_x = _build_interp_matrix((axis[None] + s[:, :1]).reshape(-1), 9, img.dtype).view(n, 5, 9)
        m_y = _build_interp_matrix((axis[None] + s[:, 1:]).reshape(-1), 9, img.dtype).view(n, 5, 9)
        return torch.einsum("nyr,rqc,nxq->nyxc", m_y, img, m_x)

    weights = torch.linspace(-1, 1, 4 * 5 * 5 * 2, dtype=torch.float64).view(4, 5, 5, 2)
    results = []
    for path in (translate_image, lambda img, s: reference(img, s)):
        s = shifts.clone().requires_grad_()
        out = translate_image(image, [axis, axis], s) if path is translate_image else path(image, s)
        results.append((out.detach(), torch.autograd.grad((out * weights).sum(), [image, s])))
    (a, grads_a), (b, grads_b) = results
    assert torch.allclose(a, b, atol=1e-12)
    for x, y in zip(grads_a, grads_b, strict=True):
        assert torch.allclose(x, y, atol=1e-10)
    assert float(grads_a[1][0].abs().sum()) > 0  # a whole-knot move still has a slope


@pytest.mark.parametrize("widths,relu_after", [((24, 32, 4), (True, False)), ((24, 4), (False,)),
                                               ((24, 32, 16, 3), (True, True, False))])
def test_decoder_function_is_the_linear_layers(widths, relu_after):
    """The decoder as one autograd function: the layers' values and every gradient, bit for bit, on the
    features' transposed view (as forward_grid passes them) and on a row-major input."""
    torch.manual_seed(0)
    layers = []
    for (a, b), relu in zip(zip(widths[:-1], widths[1:]), relu_after, strict=True):
        layers += [nn.Linear(a, b)] + ([nn.ReLU()] if relu else [])
    decoder = nn.Sequential(*layers)
    for transposed in (True, False):
        feats = torch.rand(widths[0], 300) if transposed else torch.rand(300, widths[0])
        upstream = torch.rand(300, widths[-1])
        results = []
        for path in (decoder, lambda x: decode(decoder, x)):
            decoder.zero_grad()
            x = feats.clone().requires_grad_()
            out = path(x.t() if transposed else x)
            out.backward(upstream)
            results.append([out.detach(), x.grad] + [p.grad.clone() for p in decoder.parameters()])
        for a, b in zip(*results, strict=True):
            assert torch.equal(a, b)
        with torch.no_grad():  # without autograd: the same products, no layer's output kept
            x = feats.t() if transposed else feats
            assert torch.equal(decode(decoder, x), decoder(x))
            assert not decode(decoder, x).requires_grad


def test_decoder_without_autograd_keeps_no_layer(monkeypatch):
    """Under no_grad the decoder does not go through the autograd function, which holds every layer's
    output until it returns (at a large grid's chunk, tens of MB a layer)."""
    torch.manual_seed(0)
    decoder = nn.Sequential(nn.Linear(8, 32), nn.ReLU(), nn.Linear(32, 32), nn.ReLU(), nn.Linear(32, 4))
    from rngcam.recon.methods.stfm import decoder as module
    calls = []
    monkeypatch.setattr(module._Decode, "apply", lambda *a: calls.append(a) or decoder(a[0]))
    with torch.no_grad():
        decode(decoder, torch.rand(50, 8))
    assert calls == []
    decode(decoder, torch.rand(50, 8))
    assert len(calls) == 1


def test_interpolation_matrices_built_on_the_host_are_the_tensor_formulas():
    """Matrices of constant coordinates on a CPU (numpy) equal those built with tensor operations (the
    path of coordinates with a gradient), every size, both precisions, coordinates past the border too."""
    gen = torch.Generator().manual_seed(2)
    for n in (1, 2, 5, 33, 67):
        for coords in (torch.linspace(-1, 1, n), torch.rand(n, generator=gen) * 2.4 - 1.2):
            for size in (1, 2, 3, 17, 64):
                for dtype in (torch.float32, torch.float64):
                    host = _build_interp_matrix(coords, size, dtype)
                    tensor = _build_interp_matrix(coords.clone().requires_grad_(), size, dtype).detach()
                    assert host.dtype == tensor.dtype and torch.equal(host, tensor)
        stacked = _stacked_interp(coords, [4, 8, 16], 16, n + 2, torch.float32, repeat=3)
        expected = _stacked_interp(coords.clone().requires_grad_(), [4, 8, 16], 16, n + 2, torch.float32, repeat=3)
        assert torch.equal(stacked, expected.detach())
