import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mrchaos.core.raster import View
from mrchaos.env.actions import ActionGrid
from mrchaos.learn.policy import (
    FactorisedCategorical,
    GridCategorical,
    PolicyConfig,
    SpatialHead,
    SpatialTrunk,
    build_actor_critic,
)


def test_grid_categorical_sampling_matches_probabilities():
    torch.manual_seed(0)
    logits = torch.full((1, 2, 3, 4), -30.0)
    logits[0, 1, 2, 3] = 0.0  # theta 1, y 2, x 3
    logits[0, 0, 0, 1] = np.log(3.0)  # three times as likely: theta 0, y 0, x 1
    d = GridCategorical(logits)
    s = d.sample(torch.Size([4000]))[:, 0]
    a = (s == torch.tensor([1, 0, 0])).all(-1).float().mean()
    b = (s == torch.tensor([3, 2, 1])).all(-1).float().mean()
    assert a == pytest.approx(0.75, abs=0.03) and b == pytest.approx(0.25, abs=0.03)
    assert d.log_prob(torch.tensor([[1, 0, 0]])).exp().item() == pytest.approx(0.75, abs=1e-3)
    assert d.mode.tolist() == [[1, 0, 0]]
    assert d.entropy().item() == pytest.approx(-(0.75 * np.log(0.75) + 0.25 * np.log(0.25)), abs=1e-3)


def test_grid_categorical_mode_window_reads_the_peak_of_mass_not_a_spike():
    probs = torch.full((1, 1, 9, 9), 1e-6)
    probs[0, 0, 0, 8] = 0.3  # a lone spike (x 8, y 0)
    probs[0, 0, 4:7, 2:5] = 0.07  # a 3 x 3 plateau centred on x 3, y 5: 0.63 in all
    logits = probs.log()
    assert GridCategorical(logits).mode.tolist() == [[8, 0, 0]]
    wide = GridCategorical(logits, window=3)
    assert wide.mode.tolist() == [[3, 5, 0]]
    assert torch.equal(GridCategorical(logits).mode_scores, GridCategorical(logits).scores)
    # The window reads the mode only: probabilities are those of the logits.
    assert torch.allclose(wide.log_prob(torch.tensor([[8, 0, 0]])).exp(), 0.3 / probs.sum(), atol=1e-4)


def test_grid_categorical_top_modes_are_separate_peaks_under_a_window():
    probs = torch.full((1, 2, 9, 9), 1e-6)
    probs[0, 0, 4:7, 2:5] = 0.07  # a 3 x 3 plateau centred on x 3, y 5 (orientation 0)
    probs[0, 0, 5, 3] = 0.08
    probs[0, 1, 1, 7] = 0.1  # a plus-shaped peak centred on x 7, y 1 (orientation 1): 0.2 in all
    probs[0, 1, [0, 2, 1, 1], [7, 7, 6, 8]] = 0.025
    logits = probs.log()
    flat = lambda t, y, x: (t * 9 + y) * 9 + x  # noqa: E731
    # The windowed scores' plain top 2 are the plateau's centre and one of its neighbours ...
    wide = GridCategorical(logits, window=3)
    first, second = wide.mode_scores.topk(2, -1).indices[0].tolist()
    assert first == flat(0, 5, 3) and second in (flat(0, 4, 3), flat(0, 5, 2), flat(0, 5, 4), flat(0, 6, 3))
    # ... the top modes are the two peaks, the mode first.
    assert wide.top_modes(2).tolist() == [[flat(0, 5, 3), flat(1, 1, 7)]]
    assert wide.top_modes(1).tolist() == [[flat(*reversed(wide.mode[0].tolist()))]]
    # Without a window they are the top logits.
    plain = GridCategorical(logits)
    assert torch.equal(plain.top_modes(4), logits.flatten(1).topk(4, -1).indices)


def test_factorised_categorical():
    lx, ly, lt = torch.randn(5, 51), torch.randn(5, 51), torch.randn(5, 8)
    d = FactorisedCategorical(lx, ly, lt)
    a = d.sample()
    assert a.shape == (5, 3) and (a[:, 2] < 8).all()
    expect = (
        torch.log_softmax(lx, -1).gather(-1, a[:, :1])
        + torch.log_softmax(ly, -1).gather(-1, a[:, 1:2])
        + torch.log_softmax(lt, -1).gather(-1, a[:, 2:])
    ).squeeze(-1)
    assert torch.allclose(d.log_prob(a), expect, atol=1e-5)
    assert torch.equal(d.mode, torch.stack([lx.argmax(-1), ly.argmax(-1), lt.argmax(-1)], -1))


def test_spatial_head_reads_the_grid_positions():
    """A logit peak at a point of the image selects the grid action at that point."""
    grid, view = ActionGrid(), View()
    head = SpatialHead(1, 30, grid, view)
    with torch.no_grad():
        head.conv.weight.zero_()
        head.conv.bias.zero_()
        head.conv.weight[3, 0] = 1.0  # theta index 3 reads the feature map
    f = torch.zeros(1, 1, 30, 30)
    x, y = 0.048, -0.02  # metres
    col = int((x + view.extent / 2) / view.extent * 30)
    row = int((view.extent / 2 - y) / view.extent * 30)
    f[0, 0, row, col] = 10.0
    d = GridCategorical(head(f))
    ix, iy, it = d.mode[0].tolist()
    assert it == 3
    cell = view.extent / 30
    assert abs(grid.xs[ix] - x) < cell and abs(grid.ys[iy] - y) < cell


@pytest.mark.parametrize("name,context", [("paper", 0), ("spatial", 0), ("spatial", 8)])
def test_actor_critic_shapes_and_determinism(name, context):
    grid, view = ActionGrid(), View()
    ac = build_actor_critic(PolicyConfig(name=name, channels=[8, 8, 8], hidden=32, context=context), grid, view)
    policy, value = ac.get_policy_operator(), ac.get_value_operator()
    td = TensorDict(observation=torch.randint(0, 256, (4, 2, 120, 120), dtype=torch.uint8), batch_size=[4])
    out = policy(td.clone())
    assert out["action"].shape == (4, 3) and out["action"].dtype == torch.int64
    assert (out["action"] < torch.tensor(grid.nvec)).all() and "action_log_prob" in out.keys()
    assert value(td.clone())["state_value"].shape == (4, 1)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        a1, a2 = policy(td.clone())["action"], policy(td.clone())["action"]
    assert torch.equal(a1, a2)


def test_policy_config_errors():
    with pytest.raises(ValueError, match="policy.name"):
        PolicyConfig(name="transformer")
    with pytest.raises(ValueError, match="channels"):
        PolicyConfig(channels=[8, 8])
    with pytest.raises(ValueError, match="policy.context"):
        PolicyConfig(context=-1)
    with pytest.raises(ValueError, match="odd"):
        PolicyConfig(mode_window=2)
    with pytest.raises(ValueError, match="spatial"):
        PolicyConfig(name="paper", mode_window=3)


@pytest.mark.parametrize("context", [0, 8])
def test_spatial_context_path_reaches_across_the_view(context):
    """Without the global FiLM, a logit at the view's centre sees a pixel in a corner (13 cells
    away) only through the context path; the fine layers alone see 3 cells around."""
    torch.manual_seed(0)
    grid, view = ActionGrid(), View()
    ac = build_actor_critic(PolicyConfig(channels=[8, 8, 8], hidden=16, context=context), grid, view)
    trunk = next(m for m in ac.modules() if isinstance(m, SpatialTrunk))
    with torch.no_grad():
        trunk.film.weight.zero_()
        trunk.film.bias.zero_()
        if context:  # the path starts switched off (a zero way back); as after some training
            trunk.context["up"].weight.normal_()
    policy = ac.get_policy_operator()
    obs = torch.randint(0, 256, (1, 2, 120, 120), dtype=torch.uint8)
    far = obs.clone()
    far[0, :, -8:, -8:] = 255 - far[0, :, -8:, -8:]  # bottom-right corner
    with torch.no_grad():
        a, b = (
            policy.get_dist(TensorDict(observation=o, batch_size=[1])).scores.view(1, grid.norient, grid.ny, grid.nx)
            for o in (obs, far)
        )
    cy, cx = grid.ny // 2, grid.nx // 2
    centre = (a - b)[..., cy - 1 : cy + 2, cx - 1 : cx + 2].abs().max().item()
    assert (centre > 1e-6) == bool(context)


@pytest.mark.parametrize("upsample", [1, 2])
def test_spatial_head_sampling_equals_grid_sample(upsample):
    """The separable bilinear sampling is grid_sample at the grid's image positions."""
    grid, view = ActionGrid(), View()
    head = SpatialHead(4, 30, grid, view, upsample)
    f = torch.randn(3, 4, 30, 30)
    with torch.no_grad():
        logits = head.shuffle(head.conv(f))
        gx = torch.as_tensor(grid.xs, dtype=torch.float32) / (view.extent / 2)
        gy = -torch.as_tensor(grid.ys, dtype=torch.float32) / (view.extent / 2)
        yy, xx = torch.meshgrid(gy, gx, indexing="ij")
        where = torch.stack([xx, yy], -1)[None].expand(3, -1, -1, -1)
        expect = torch.nn.functional.grid_sample(logits, where, mode="bilinear", align_corners=False)
        assert torch.allclose(head(f), expect, atol=1e-4)


def test_grid_categorical_fused_log_prob_and_entropy_gradients():
    """log_prob with gradients also gives the entropy; both, and their gradients, are the plain ones."""
    torch.manual_seed(1)
    z = torch.randn(5, 8, 7, 6, requires_grad=True)
    a = torch.stack([torch.randint(0, 6, (5,)), torch.randint(0, 7, (5,)), torch.randint(0, 8, (5,))], -1)
    d = GridCategorical(z)
    lp, h = d.log_prob(a), d.entropy()
    (lp.sum() + 0.3 * h.sum()).backward()
    g = z.grad.clone()
    z.grad = None
    ref = torch.log_softmax(z.flatten(-3), -1)
    flat = a[:, 2] * 42 + a[:, 1] * 6 + a[:, 0]
    lp_ref, h_ref = ref.gather(-1, flat[:, None])[:, 0], -(ref.exp() * ref).sum(-1)
    (lp_ref.sum() + 0.3 * h_ref.sum()).backward()
    assert torch.allclose(lp, lp_ref, atol=1e-6) and torch.allclose(h, h_ref, atol=1e-6)
    assert torch.allclose(g, z.grad, atol=1e-6)
    with torch.no_grad():
        assert torch.allclose(d.log_prob(a), lp_ref, atol=1e-6)


@pytest.mark.parametrize("block", ["attention", "unet"])
def test_global_view_starts_as_the_plain_net_and_reaches_across_the_view(block):
    """A global block is switched off at the start (the same logits as the net without it, given
    the same weights); switched on, a logit at the centre sees a far corner without the context
    path or the FiLM."""
    torch.manual_seed(0)
    grid, view = ActionGrid(), View()
    small = dict(channels=[8, 8, 8], hidden=16, global_width=16, global_layers=1)
    plain = build_actor_critic(PolicyConfig(**small), grid, view)
    ac = build_actor_critic(PolicyConfig(global_view=block, **small), grid, view)
    missing = ac.load_state_dict(plain.state_dict(), strict=False).missing_keys
    assert missing and all("global_view" in k for k in missing)
    obs = torch.randint(0, 256, (1, 2, 120, 120), dtype=torch.uint8)

    def scores(net, o):
        with torch.no_grad():
            d = net.get_policy_operator().get_dist(TensorDict(observation=o, batch_size=[1]))
        return d.scores.view(1, grid.norient, grid.ny, grid.nx)

    assert torch.allclose(scores(ac, obs), scores(plain, obs), atol=1e-6)
    trunk = next(m for m in ac.modules() if isinstance(m, SpatialTrunk))
    with torch.no_grad():
        trunk.film.weight.zero_()
        trunk.film.bias.zero_()
        trunk.global_view.out.weight.normal_()
    far = obs.clone()
    far[0, :, -8:, -8:] = 255 - far[0, :, -8:, -8:]
    cy, cx = grid.ny // 2, grid.nx // 2

    def centre(net):
        return (scores(net, obs) - scores(net, far))[..., cy - 1 : cy + 2, cx - 1 : cx + 2].abs().max().item()

    plain_trunk = next(m for m in plain.modules() if isinstance(m, SpatialTrunk))
    with torch.no_grad():
        plain_trunk.film.weight.zero_()
        plain_trunk.film.bias.zero_()
    # Out of the fine layers' reach the plain net's centre is untouched to the bit; the global
    # block moves it (the U-Net's nearest-neighbour way up passes little of a corner: about 1e-7).
    assert centre(plain) == 0.0 and centre(ac) > 1e-9


def test_coordinate_channels_tell_positions_apart():
    """Without coordinates a convolution answers an empty image alike everywhere inside the
    border; with them the same empty image gets position-dependent logits."""
    torch.manual_seed(0)
    grid, view = ActionGrid(), View()
    obs = torch.zeros(1, 2, 120, 120, dtype=torch.uint8)
    spread = []
    for coords in (False, True):
        ac = build_actor_critic(PolicyConfig(channels=[8, 8, 8], hidden=16, coords=coords), grid, view)
        with torch.no_grad():
            s = ac.get_policy_operator().get_dist(TensorDict(observation=obs, batch_size=[1])).scores
        inner = s.view(grid.norient, grid.ny, grid.nx)[:, 15:-15, 15:-15]
        spread.append((inner.amax((-2, -1)) - inner.amin((-2, -1))).max().item())
    assert spread[0] < 1e-5 < spread[1]


def test_global_view_config_errors():
    with pytest.raises(ValueError, match="global_view"):
        PolicyConfig(global_view="mamba")
    with pytest.raises(ValueError, match="spatial"):
        PolicyConfig(name="paper", global_view="unet")
    with pytest.raises(ValueError, match="global_width"):
        PolicyConfig(global_view="attention", global_width=0)
