"""Policies: the paper's factorised network and our fully convolutional one, as TorchRL modules.

Both read ``observation`` (uint8, N x 2 x H x W) and share a trunk between the
actor and the value head (``ActorValueOperator``).

* ``paper``: three conv layers, an MLP with 512 hidden units, and factorised
  categorical heads for x, y and theta (the reference code's MultiDiscrete policy).
* ``spatial``: a fully convolutional net whose last layer gives one logit per
  (theta, y, x) grid action, read at the grid's positions in the image, so that
  "place here" is learnt the same way at every position; a global context vector
  (FiLM) tells every position what stage of the assembly it is in.

With free order (``env.order: free``, ``build_actor_critic(..., pieces=P)``) both also read the
pieces left (``remaining``, into the MLP or the FiLM context) and the action mask: the paper
net gets a piece head, the spatial net one set of orientation channels per piece, and the pieces
the mask forbids get :data:`MASKED_LOGIT`; actions are (piece, x, y, theta).

On a refined grid (``env.grid.fine_xy``, ``fine_theta``) the spatial net also scores the offset
inside the coarse cell it chose, from the features at that cell (:class:`CoarseFineCategorical`):
actions are (x, y, theta, fine).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torch.distributions import Categorical, Distribution, constraints
from torchrl.modules import ActorValueOperator, ProbabilisticActor, ValueOperator

from mrchaos.core.raster import View
from mrchaos.env.actions import ActionGrid
from mrchaos.learn.globalview import GLOBAL_VIEWS, build_global_view

__all__ = [
    "PolicyConfig",
    "FactorisedCategorical",
    "GridCategorical",
    "PieceGridCategorical",
    "CoarseFineCategorical",
    "MASKED_LOGIT",
    "mask_pieces",
    "build_actor_critic",
    "compile_networks",
    "count_parameters",
    "unravel_actions",
    "ravel_actions",
    "POLICIES",
]

POLICIES = ("paper", "spatial")


@dataclass
class PolicyConfig:
    """Network choice and sizes.

    Attributes:
        name: "paper" or "spatial".
        pool: average-pool the 120x120 input by this factor first (1 = none).
        channels: conv widths of the trunk.
        hidden: MLP width (paper) / context width (spatial).
        upsample: the spatial head's logit lattice is this many times finer than the trunk's
            (sub-pixel convolution): 1 reads the 8.7 mm trunk cells directly, 2 gives 4.3 mm
            cells, about the action grid's 4 mm step, so a logit peak can sit on one action.
        context: width of the spatial trunk's coarse context path (0 = none, as the first shipped
            networks): a stride-2 step to 17 mm cells, three residual 3x3 blocks dilated 1, 2 and 4
            that together see about 13 cm each way (half the view), added back to the fine
            features. The fine layers alone see about 3 cm each way, less than a large triangle,
            so where a piece fits among the other pieces' slots is out of their reach.
        mode_window: the spatial policy's deterministic action is the grid action whose
            window x window neighbourhood (same orientation) holds the most probability; 1 is
            the single most probable action. Sampling, log-probabilities and training are
            unchanged. A window of 3 (plus or minus one 4 mm step) reads the peak of the
            placement's probability rather than its highest single spike.
        global_view: a block of the spatial trunk that lets every cell see the whole image
            (:mod:`mrchaos.learn.globalview`): "none", "attention" (transformer layers over
            patches) or "unet"; added after the context path.
        global_width: the global block's width (tokens' width, or the U-Net's first width).
        global_layers: transformer layers of the "attention" block.
        coords: the spatial trunk also reads two coordinate channels (x and y across the view).
    """

    name: str = "spatial"
    pool: int = 2
    channels: list[int] = field(default_factory=lambda: [16, 32, 32])
    hidden: int = 512
    upsample: int = 1
    context: int = 0
    mode_window: int = 1
    global_view: str = "none"
    global_width: int = 64
    global_layers: int = 2
    coords: bool = False

    def __post_init__(self) -> None:
        if self.name not in POLICIES:
            raise ValueError(f"policy.name must be one of {POLICIES}, got {self.name!r}")
        if len(self.channels) != 3 or min(self.channels) < 1:
            raise ValueError(f"policy.channels must be three positive widths, got {self.channels}")
        if self.pool < 1:
            raise ValueError(f"policy.pool must be >= 1, got {self.pool}")
        if self.upsample < 1:
            raise ValueError(f"policy.upsample must be >= 1, got {self.upsample}")
        if self.context < 0:
            raise ValueError(f"policy.context must be >= 0 (0 = no context path), got {self.context}")
        if self.mode_window < 1 or self.mode_window % 2 == 0:
            raise ValueError(f"policy.mode_window must be odd and >= 1, got {self.mode_window}")
        if self.global_view not in GLOBAL_VIEWS:
            raise ValueError(f"policy.global_view must be one of {GLOBAL_VIEWS}, got {self.global_view!r}")
        if self.global_width < 1 or self.global_layers < 1:
            raise ValueError(
                f"policy.global_width and global_layers must be >= 1, got {self.global_width}, {self.global_layers}"
            )
        if self.name != "spatial" and (self.global_view != "none" or self.coords):
            raise ValueError(f"policy.global_view and policy.coords need the spatial policy, got {self.name!r}")
        if self.name != "spatial" and self.mode_window != 1:
            raise ValueError(
                f"policy.mode_window needs the spatial policy (one score per grid action), got {self.name!r}"
            )


class FactorisedCategorical(Distribution):
    """Independent categoricals over x, y and theta; samples are (..., 3) int64 indices. With free
    order (``logits_p``, masked pieces already at :data:`MASKED_LOGIT`) a piece categorical comes
    first: (..., 4) = (piece, x, y, theta)."""

    arg_constraints: dict = {}
    has_enumerate_support = False

    def __init__(
        self,
        logits_x: torch.Tensor,
        logits_y: torch.Tensor,
        logits_t: torch.Tensor,
        logits_p: torch.Tensor | None = None,
    ) -> None:
        given = (logits_x, logits_y, logits_t) if logits_p is None else (logits_p, logits_x, logits_y, logits_t)
        self.parts = tuple(Categorical(logits=lg.float()) for lg in given)
        super().__init__(batch_shape=logits_x.shape[:-1], event_shape=torch.Size([len(given)]), validate_args=False)

    @property
    def support(self):
        return constraints.integer_interval(0, max(p.logits.shape[-1] for p in self.parts) - 1)

    def sample(self, sample_shape: torch.Size | list[int] | tuple[int, ...] = torch.Size()) -> torch.Tensor:
        return torch.stack([p.sample(torch.Size(sample_shape)) for p in self.parts], -1)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        value = value.long()
        return sum(p.log_prob(value[..., i]) for i, p in enumerate(self.parts))

    def entropy(self) -> torch.Tensor:
        return sum(p.entropy() for p in self.parts)

    @property
    def mode(self) -> torch.Tensor:
        return torch.stack([p.logits.argmax(-1) for p in self.parts], -1)

    @property
    def deterministic_sample(self) -> torch.Tensor:
        return self.mode


def _entropy(lp: torch.Tensor) -> torch.Tensor:
    """Entropy of categoricals given by normalised log-probabilities ``lp`` (..., N)."""
    return -(lp.exp() * lp).sum(-1)


def _log_prob_entropy(scores: torch.Tensor, flat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Log-probability of ``flat`` and entropy of the categorical with unnormalised ``scores`` (..., N)."""
    lp = scores - torch.logsumexp(scores, -1, keepdim=True)
    return lp.gather(-1, flat.unsqueeze(-1)).squeeze(-1), _entropy(lp)


# The PPO loss's log-probability and entropy over 20,808 actions, their elementwise passes fused
# by torch.compile when the networks are compiled (compile_networks sets it): in eager mode
# they cost about a quarter of a PPO step (measured).
_fused_log_prob_entropy = None


#: The logit of a piece a free-order action may not choose: finite, so that its probability is 0
#: and p log p stays 0 rather than NaN.
MASKED_LOGIT = -1e9


def mask_pieces(logits: torch.Tensor, mask: torch.Tensor, per_piece: int = 1) -> torch.Tensor:
    """``logits`` (B, P * per_piece, ...) with the channels of pieces that ``mask`` forbids set to
    :data:`MASKED_LOGIT` (in fp32). ``mask`` is (..., P) bool, or a whole free-order action mask
    (..., P + X + Y + O), whose first P entries are the pieces'."""
    p = logits.shape[1] // per_piece
    mask = mask.reshape(-1, mask.shape[-1])[:, :p]
    b = mask.shape[0]
    keep = mask.repeat_interleave(per_piece, 1).reshape(b, p * per_piece, *([1] * (logits.dim() - 2)))
    return torch.where(keep, logits.float(), torch.full((), MASKED_LOGIT))


def unravel_actions(flat: torch.Tensor, nx: int, ny: int) -> torch.Tensor:
    """(..., 3) grid actions (x, y, theta) of indices into the flattened (theta, y, x) grid of the
    spatial head's scores."""
    return torch.stack([flat % nx, (flat // nx) % ny, flat // (nx * ny)], -1)


def ravel_actions(actions: torch.Tensor, nx: int, ny: int) -> torch.Tensor:
    """Indices into the flattened (theta, y, x) grid of (..., 3) grid actions (x, y, theta): the
    inverse of :func:`unravel_actions`."""
    actions = actions.long()
    return actions[..., 2] * (nx * ny) + actions[..., 1] * nx + actions[..., 0]


class GridCategorical(Distribution):
    """One categorical over the flattened (theta, y, x) grid; samples are (..., 3) indices (x, y, theta).

    Sampling inverts the cumulative distribution with one uniform draw per sample:
    ``torch.multinomial`` over 20,808 categories costs about 0.5 ms per sample on this CPU,
    the Gumbel-max trick (a uniform draw and two logarithms per category) 0.3 ms, the
    inverse CDF 0.035 ms (measured). A :meth:`log_prob` taken with gradients also computes
    the entropy from the same log-probabilities, and :meth:`entropy` returns it (the PPO
    loss asks for both, in that order). ``window`` > 1 makes :attr:`mode` the action whose
    window x window neighbourhood holds the most probability (:attr:`mode_scores`).
    """

    arg_constraints: dict = {}
    has_enumerate_support = False

    def __init__(self, logits: torch.Tensor, window: int = 1) -> None:
        # logits: (..., T, Y, X), unnormalised
        self.grid_shape = logits.shape[-3:]
        self.window = window
        self.scores = logits.flatten(-3).float()
        self._entropy: torch.Tensor | None = None
        super().__init__(batch_shape=logits.shape[:-3], event_shape=torch.Size([3]), validate_args=False)

    @property
    def logits(self) -> torch.Tensor:
        """Normalised log-probabilities (..., T*Y*X)."""
        return torch.log_softmax(self.scores, -1)

    @property
    def support(self):
        return constraints.integer_interval(0, max(self.grid_shape) - 1)

    def _unravel(self, flat: torch.Tensor) -> torch.Tensor:
        _, y, x = self.grid_shape
        return unravel_actions(flat, x, y)

    def sample(self, sample_shape: torch.Size | list[int] | tuple[int, ...] = torch.Size()) -> torch.Tensor:
        with torch.no_grad():
            cdf = torch.softmax(self.scores, -1).cumsum(-1)
            cdf = cdf.expand(*sample_shape, *cdf.shape).contiguous()  # a no-op without sample_shape
            u = torch.rand(*cdf.shape[:-1], 1, device=cdf.device) * cdf[..., -1:]
            # right=True: the first action whose cumulative mass exceeds u, never one of zero mass.
            flat = torch.searchsorted(cdf, u, right=True).squeeze(-1).clamp_max_(cdf.shape[-1] - 1)
            return self._unravel(flat)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        _, y, x = self.grid_shape
        flat = ravel_actions(value, x, y)
        if not torch.is_grad_enabled():
            lse = torch.logsumexp(self.scores, -1)
            return torch.gather(self.scores, -1, flat.unsqueeze(-1)).squeeze(-1) - lse
        fn = _fused_log_prob_entropy or _log_prob_entropy
        lp, self._entropy = fn(self.scores, flat)
        return lp

    def entropy(self) -> torch.Tensor:
        if self._entropy is not None and torch.is_grad_enabled():
            return self._entropy
        return _entropy(self.logits)

    @property
    def mode_scores(self) -> torch.Tensor:
        """(..., T*Y*X) scores whose order is the policy's preference among actions: the logits,
        or with a window the log of the probability within each action's neighbourhood. The
        mode is their argmax; a planner takes its candidates from :meth:`top_modes`."""
        if self.window == 1:
            return self.scores
        _, y, x = self.grid_shape
        p = torch.softmax(self.scores, -1).reshape(-1, 1, y, x)
        # Zero padding: the window's sum at the grid's edge counts only actions that exist.
        mass = F.avg_pool2d(p, self.window, stride=1, padding=self.window // 2)
        return mass.clamp_min(1e-30).log().reshape(self.scores.shape)

    def scores_at(self, actions: torch.Tensor) -> torch.Tensor:
        """(..., k) :attr:`mode_scores` of the grid actions ``actions`` (..., k, 3): how the policy
        ranks them (a planner's candidates, say)."""
        _, y, x = self.grid_shape
        return self.mode_scores.gather(-1, ravel_actions(actions, x, y))

    def top_actions(self, k: int) -> torch.Tensor:
        """(..., k, event) the actions of :meth:`top_modes`, best first (with free order, the piece
        is part of each)."""
        return self._unravel(self.top_modes(k))

    def top_modes(self, k: int) -> torch.Tensor:
        """(..., k) flat indices of the ``k`` best actions in the policy's order, the mode first.

        With a window, only actions whose score is the largest within their own window (same
        orientation) are candidates, so that the k are k separate peaks rather than the
        neighbours of one: windowed scores are smooth. With window 1 this is the top k logits."""
        scores = self.mode_scores
        if self.window > 1:
            _, y, x = self.grid_shape
            grid = scores.reshape(-1, 1, y, x)
            peak = grid == F.max_pool2d(grid, self.window, stride=1, padding=self.window // 2)
            # Off-peak actions stay below every peak (scores >= log 1e-30), in their own order.
            scores = torch.where(peak, grid, grid - 1e3).reshape(scores.shape)
        return scores.topk(k, -1).indices

    @property
    def mode(self) -> torch.Tensor:
        return self._unravel(self.mode_scores.argmax(-1))

    @property
    def deterministic_sample(self) -> torch.Tensor:
        return self.mode


class PieceGridCategorical(GridCategorical):
    """Free order's :class:`GridCategorical`: the logits (..., P * T, Y, X) hold one set of T
    orientation channels per piece (masked pieces already at :data:`MASKED_LOGIT`), and actions
    are (..., 4) = (piece, x, y, theta); channel c is piece c // T, orientation c % T."""

    def __init__(self, logits: torch.Tensor, window: int = 1, pieces: int = 1) -> None:
        super().__init__(logits, window)
        self.pieces = pieces
        self.norient = logits.shape[-3] // pieces
        self._event_shape = torch.Size([4])

    def _unravel(self, flat: torch.Tensor) -> torch.Tensor:
        a = super()._unravel(flat)
        c = a[..., 2]
        return torch.stack([c // self.norient, a[..., 0], a[..., 1], c % self.norient], -1)

    def _grid(self, value: torch.Tensor) -> torch.Tensor:
        """(..., 4) free-order actions as (..., 3) (x, y, channel) of the underlying grid."""
        value = value.long()
        return torch.stack([value[..., 1], value[..., 2], value[..., 0] * self.norient + value[..., 3]], -1)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        return super().log_prob(self._grid(value))

    def scores_at(self, actions: torch.Tensor) -> torch.Tensor:
        return super().scores_at(self._grid(actions))


class CoarseFineCategorical(GridCategorical):
    """A :class:`GridCategorical` over the coarse grid, then the offset inside the chosen cell:
    actions are (..., 4) = (x, y, theta, fine), ``fine = fxy + fine_xy**2 * ft`` as
    :meth:`mrchaos.env.actions.ActionGrid.fine_offsets` reads it.

    Given the coarse action, the position offset ``fxy`` (``fine_xy**2`` choices) and the angle
    offset ``ft`` (``fine_theta`` choices, scored per orientation) are independent categoricals
    whose logits are the ``fine`` feature map (..., fine_xy**2 + T * fine_theta, n, n) read
    bilinearly at the coarse action's grid position (``wx`` (X, n), ``wy`` (Y, n)). Only the chosen
    cell's offsets are ever scored, so a refined action costs ``fine_xy**2 + T * fine_theta``
    outputs more, not a grid that many times larger.

    :meth:`log_prob` is the joint's; :meth:`entropy` adds the fine part's entropy at the actions
    :meth:`log_prob` last scored (the PPO loss asks in that order), else at the mode. The planner's
    candidates (:meth:`top_actions`) are the coarse ones, each with its most probable offset.
    """

    def __init__(
        self,
        logits: torch.Tensor,
        fine: torch.Tensor,
        wx: torch.Tensor,
        wy: torch.Tensor,
        fine_xy: int,
        fine_theta: int,
        window: int = 1,
    ) -> None:
        super().__init__(logits, window)
        self.fine = fine.float()
        self.wx, self.wy = wx.to(self.fine.device), wy.to(self.fine.device)
        self.nxy, self.fine_theta = fine_xy * fine_xy, fine_theta
        self._fine_entropy: torch.Tensor | None = None
        self._event_shape = torch.Size([4])

    def fine_logits(self, coarse: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Unnormalised logits (..., fine_xy**2) of the position offset and (..., fine_theta) of the
        angle offset at coarse actions (..., 3); leading dims beyond the batch's go first."""
        coarse = coarse.long()
        rx, ry = self.wx[coarse[..., 0]], self.wy[coarse[..., 1]]  # (..., n)
        vals = torch.einsum("...a,...cab,...b->...c", ry, self.fine, rx)
        xy, t = vals[..., : self.nxy], vals[..., self.nxy :]
        t = t.reshape(*t.shape[:-1], -1, self.fine_theta)  # (..., T, fine_theta)
        idx = coarse[..., 2, None, None].expand(*t.shape[:-2], 1, self.fine_theta)
        return xy, t.gather(-2, idx).squeeze(-2)

    def _fine_parts(self, coarse: torch.Tensor) -> tuple[Categorical, Categorical]:
        xy, t = self.fine_logits(coarse)
        return Categorical(logits=xy), Categorical(logits=t)

    def sample(self, sample_shape: torch.Size | list[int] | tuple[int, ...] = torch.Size()) -> torch.Tensor:
        coarse = super().sample(sample_shape)
        with torch.no_grad():
            pxy, pt = self._fine_parts(coarse)
            fine = pxy.sample() + self.nxy * pt.sample()
        return torch.cat([coarse, fine[..., None]], -1)

    def fine_log_prob(self, value: torch.Tensor) -> torch.Tensor:
        """Log-probability of the offsets of actions (..., 4) given their coarse cells."""
        value = value.long()
        pxy, pt = self._fine_parts(value[..., :3])
        fine = value[..., 3]
        if torch.is_grad_enabled():
            self._fine_entropy = pxy.entropy() + pt.entropy()
        return pxy.log_prob(fine % self.nxy) + pt.log_prob(fine // self.nxy)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        return super().log_prob(value[..., :3].long()) + self.fine_log_prob(value)

    def entropy(self) -> torch.Tensor:
        fine = self._fine_entropy if self._fine_entropy is not None and torch.is_grad_enabled() else None
        if fine is None:
            pxy, pt = self._fine_parts(super().mode)
            fine = pxy.entropy() + pt.entropy()
        return super().entropy() + fine

    def with_fine_mode(self, coarse: torch.Tensor) -> torch.Tensor:
        """Coarse actions (..., 3) completed by each one's most probable offset: (..., 4)."""
        xy, t = self.fine_logits(coarse)
        fine = xy.argmax(-1) + self.nxy * t.argmax(-1)
        return torch.cat([coarse, fine[..., None]], -1)

    def scores_at(self, actions: torch.Tensor) -> torch.Tensor:
        return super().scores_at(actions[..., :3])

    def top_actions(self, k: int) -> torch.Tensor:
        coarse = super().top_actions(k)  # (..., k, 3)
        # fine_logits takes extra leading dims first: put the candidates' dim in front and back.
        return self.with_fine_mode(coarse.movedim(-2, 0)).movedim(0, -2)

    @property
    def mode(self) -> torch.Tensor:
        return self.with_fine_mode(super().mode)


class FineHead(nn.Module):
    """The refined grid's fine feature map: per trunk cell, logits of the ``fine_xy**2`` position
    offsets and of the ``fine_theta`` angle offsets of every orientation, read by
    :class:`CoarseFineCategorical` at the coarse action's cell. Zero-initialised: a policy starts
    at the coarse pose's neighbourhood uniformly and learns where inside the cell to go."""

    def __init__(self, channels: int, grid: ActionGrid) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, grid.fine_xy**2 + grid.norient * grid.fine_theta, 1)
        nn.init.zeros_(self.conv.weight)
        nn.init.zeros_(self.conv.bias)  # type: ignore[arg-type]  # Conv2d has a bias unless told otherwise

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        lead = f.shape[:-3]
        out = self.conv(f.reshape(-1, *f.shape[-3:]))
        return out.reshape(*lead, *out.shape[1:])


def _prep(obs: torch.Tensor, pool: int) -> torch.Tensor:
    # Straight to the autocast dtype (bf16 holds 0 and 255 exactly): no fp32 copy of the batch.
    kind = obs.device.type
    dtype = torch.get_autocast_dtype(kind) if torch.is_autocast_enabled(kind) else torch.float32
    x = obs.to(dtype) * (1.0 / 255.0)
    return F.avg_pool2d(x, pool) if pool > 1 else x


class PaperTrunk(nn.Module):
    """3 conv layers (8/4, 4/2, 3/1 kernels/strides, as the reference CNN) and a 512-unit MLP layer."""

    def __init__(self, cfg: PolicyConfig, size: int, pieces: int = 0) -> None:
        super().__init__()
        c1, c2, c3 = cfg.channels
        self.pool = cfg.pool
        self.pieces = pieces
        self.conv = nn.Sequential(
            nn.Conv2d(2, c1, 8, stride=4),
            nn.ReLU(),
            nn.Conv2d(c1, c2, 4, stride=2),
            nn.ReLU(),
            nn.Conv2d(c2, c3, 3, stride=1),
            nn.ReLU(),
            nn.Flatten(),
        )
        with torch.no_grad():
            n = self.conv(torch.zeros(1, 2, size // cfg.pool, size // cfg.pool)).shape[-1]
        # With free order the pieces left join the image features.
        self.fc = nn.Sequential(nn.Linear(n + pieces, cfg.hidden), nn.ReLU())

    def forward(self, obs: torch.Tensor, remaining: torch.Tensor | None = None) -> torch.Tensor:
        lead = obs.shape[:-3]
        x = self.conv(_prep(obs.reshape(-1, *obs.shape[-3:]), self.pool))
        if self.pieces:
            assert remaining is not None  # free order's modules read it (build_actor_critic)
            x = torch.cat([x, remaining.reshape(-1, self.pieces).to(x.dtype)], -1)
        return self.fc(x).reshape(*lead, -1)


class PaperHeads(nn.Module):
    """Linear heads for x, y and theta, and with free order for the piece (masked)."""

    def __init__(self, hidden: int, grid: ActionGrid, pieces: int = 0) -> None:
        super().__init__()
        self.x, self.y, self.t = nn.Linear(hidden, grid.nx), nn.Linear(hidden, grid.ny), nn.Linear(hidden, grid.norient)
        self.pieces = pieces
        self.p = nn.Linear(hidden, pieces) if pieces else None

    def forward(self, h: torch.Tensor, action_mask: torch.Tensor | None = None):
        if self.p is None:
            return self.x(h), self.y(h), self.t(h)
        assert action_mask is not None  # free order's modules read it (build_actor_critic)
        lead = h.shape[:-1]
        piece = mask_pieces(self.p(h).reshape(-1, self.pieces), action_mask).reshape(*lead, self.pieces)
        return self.x(h), self.y(h), self.t(h), piece


class SpatialTrunk(nn.Module):
    """Fully convolutional features on a 4x4-pixel lattice (8.7 mm cells) with a FiLM global context.

    The first layer cuts the image into 4x4 patches (as a stride-4 conv), which keeps
    the later 3x3 layers at 30x30 and the whole net cheap on a CPU; the dilated last
    layer sees about 3 cm each way around a cell, and the optional context path
    (``PolicyConfig.context``) about 13 cm.
    """

    def __init__(self, cfg: PolicyConfig, size: int, pieces: int = 0) -> None:
        super().__init__()
        c1, c2, c3 = cfg.channels
        self.pool = cfg.pool
        self.pieces = pieces
        patch = max(1, 4 // cfg.pool)
        self.coords = cfg.coords
        self.enc = nn.Sequential(
            nn.Conv2d(4 if cfg.coords else 2, c1, patch, stride=patch),
            nn.ReLU(),
            nn.Conv2d(c1, c2, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(c2, c3, 3, padding=2, dilation=2),
            nn.ReLU(),
        )
        self.context = None
        if cfg.context:
            w = cfg.context
            self.context = nn.ModuleDict(
                {
                    "down": nn.Conv2d(c3, w, 3, stride=2, padding=1),
                    "blocks": nn.ModuleList(nn.Conv2d(w, w, 3, padding=d, dilation=d) for d in (1, 2, 4)),
                    "up": nn.Conv2d(w, c3, 1),
                }
            )
            # Zero-initialised way back: the net starts as the one without the path and learns
            # how much context to add.
            up = self.context["up"]
            assert isinstance(up, nn.Conv2d)
            nn.init.zeros_(up.weight)
            nn.init.zeros_(up.bias)  # type: ignore[arg-type]  # Conv2d has a bias unless told otherwise
        # With free order the pieces left join the pooled features: every position's FiLM knows them.
        self.ctx = nn.Sequential(nn.Linear(2 * c3 + pieces, cfg.hidden), nn.ReLU())
        self.film = nn.Linear(cfg.hidden, 2 * c3)
        self.out_channels = c3
        self.cells = size // cfg.pool // patch  # feature cells across the image
        self.global_view = build_global_view(cfg.global_view, c3, cfg.global_width, cfg.global_layers, self.cells)
        self.hidden = cfg.hidden

    def forward(self, obs: torch.Tensor, remaining: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        lead = obs.shape[:-3]
        # channels_last halves the cost of these small convolutions on CPU (measured).
        x = _prep(obs.reshape(-1, *obs.shape[-3:]), self.pool)
        if self.coords:
            ramp = torch.linspace(-1.0, 1.0, x.shape[-1], dtype=x.dtype, device=x.device)
            grid = torch.stack([ramp.expand(x.shape[-2], -1), ramp[:, None].expand(-1, x.shape[-1])])
            x = torch.cat([x, grid.expand(len(x), -1, -1, -1)], 1)
        f = self.enc(x.contiguous(memory_format=torch.channels_last))
        if self.context is not None:
            h = F.relu(self.context["down"](f))
            blocks = self.context["blocks"]
            assert isinstance(blocks, nn.ModuleList)
            for block in blocks:
                h = F.relu(h + block(h))
            f = F.relu(f + F.interpolate(self.context["up"](h), size=f.shape[-2:], mode="nearest"))
        if self.global_view is not None:
            f = F.relu(f + self.global_view(f))
        pooled = [f.mean((-2, -1)), f.amax((-2, -1))]
        if self.pieces:
            assert remaining is not None  # free order's modules read it (build_actor_critic)
            pooled.append(remaining.reshape(-1, self.pieces).to(f.dtype))
        g = self.ctx(torch.cat(pooled, -1))
        scale, shift = self.film(g).chunk(2, -1)
        f = F.relu(f * (1 + scale[..., None, None]) + shift[..., None, None])
        return f.reshape(*lead, *f.shape[1:]), g.reshape(*lead, -1)


def bilinear_matrix(coords: torch.Tensor, n: int) -> torch.Tensor:
    """(len(coords), n) weights that sample a length-``n`` lattice at normalised ``coords`` in [-1, 1]
    bilinearly, as ``grid_sample`` does (``align_corners=False``, zeros outside)."""
    p = ((coords.double() + 1) * n - 1) / 2
    i0 = p.floor().long()
    w1 = p - i0
    m = torch.zeros(len(coords), n, dtype=torch.float64)
    rows = torch.arange(len(coords))
    for i, w in ((i0, 1 - w1), (i0 + 1, w1)):
        ok = (i >= 0) & (i < n)
        m[rows[ok], i[ok]] += w[ok]
    return m.float()


def grid_sampling(grid: ActionGrid, view: View, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``wx`` (X, n) and ``wy`` (Y, n): the bilinear weights that read a length-``n`` lattice over
    the image at the grid's x and y positions (:func:`bilinear_matrix`)."""
    # Normalised image coordinates of the grid (x right, y down, [-1, 1] at the image's edges).
    gx = torch.as_tensor(grid.xs, dtype=torch.float64) / (view.extent / 2)
    gy = -torch.as_tensor(grid.ys, dtype=torch.float64) / (view.extent / 2)
    return bilinear_matrix(gx, n), bilinear_matrix(gy, n)


class SpatialHead(nn.Module):
    """Per-position logits for every angle, sampled at the action grid's image positions.

    The grid is a product of x and y positions, so bilinear sampling is separable: two small
    matrix products (``wy @ logits @ wx.T``) that equal ``grid_sample`` to float rounding, and
    whose backward pass costs a fraction of ``grid_sample``'s on the CPU (measured).
    """

    def __init__(
        self, channels: int, cells: int, grid: ActionGrid, view: View, upsample: int = 1, pieces: int = 0
    ) -> None:
        super().__init__()
        # Free order: one set of orientation channels per piece, the pieces not allowed masked.
        self.pieces, self.norient = pieces, grid.norient
        # upsample > 1: each trunk cell predicts an upsample x upsample block of logits (pixel shuffle).
        self.conv = nn.Conv2d(channels, grid.norient * max(pieces, 1) * upsample**2, 1)
        self.shuffle = nn.PixelShuffle(upsample) if upsample > 1 else nn.Identity()
        wx, wy = grid_sampling(grid, view, cells * upsample)
        # Derived from the grid and the view, so not part of the weights.
        self.register_buffer("wx", wx, persistent=False)  # (X, n)
        self.register_buffer("wy", wy, persistent=False)  # (Y, n)

    def forward(self, f: torch.Tensor, action_mask: torch.Tensor | None = None) -> torch.Tensor:
        lead = f.shape[:-3]
        f = f.reshape(-1, *f.shape[-3:])
        logits = self.shuffle(self.conv(f))  # (B, T, n, n)
        out = self.wy.to(logits.dtype) @ logits @ self.wx.to(logits.dtype).T  # (B, T, Y, X)
        if self.pieces:
            assert action_mask is not None  # free order's modules read it (build_actor_critic)
            out = mask_pieces(out, action_mask, self.norient)
        return out.reshape(*lead, *out.shape[1:])

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # Checkpoints written before the separable sampling keep grid_sample's coordinates.
        state_dict.pop(prefix + "where", None)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


class _Value(nn.Module):
    def __init__(self, n: int) -> None:
        super().__init__()
        self.v = nn.Sequential(nn.Linear(n, 256), nn.ReLU(), nn.Linear(256, 1))

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        # fp32 out of bf16 autocast: GAE and the critic loss sum these.
        return self.v(h).float()


_NETWORKS = (PaperTrunk, PaperHeads, SpatialTrunk, SpatialHead, FineHead)


def build_actor_critic(
    cfg: PolicyConfig, grid: ActionGrid, view: View, action_spec=None, pieces: int = 0
) -> ActorValueOperator:
    """The actor-critic as an ``ActorValueOperator`` (shared trunk, policy head, value head).

    ``get_policy_operator()`` samples ``action`` (and ``action_log_prob``);
    ``get_value_operator()`` writes ``state_value``. ``pieces`` > 0 builds the free-order policy of
    a set of that many pieces (``env.order: free``): it also reads ``remaining`` and
    ``action_mask``, and its actions are (piece, x, y, theta).
    """
    if grid.refined and (cfg.name != "spatial" or pieces):
        raise ValueError(
            "a refined grid (env.grid.fine_xy, fine_theta) needs the spatial policy in the set's order "
            f"(policy.name: spatial, env.order: fixed), got {cfg.name!r}" + (" in free order" if pieces else "")
        )
    size = view.size
    obs_keys = ["observation", "remaining"] if pieces else ["observation"]
    mask_keys = ["action_mask"] if pieces else []
    if cfg.name == "paper":
        common = TensorDictModule(PaperTrunk(cfg, size, pieces), in_keys=obs_keys, out_keys=["hidden"])
        logit_keys = ["logits_x", "logits_y", "logits_t"] + (["logits_p"] if pieces else [])
        head = TensorDictModule(
            PaperHeads(cfg.hidden, grid, pieces), in_keys=["hidden", *mask_keys], out_keys=logit_keys
        )
        actor = ProbabilisticActor(
            head,
            in_keys=logit_keys,
            out_keys=["action"],
            spec=action_spec,
            distribution_class=FactorisedCategorical,
            return_log_prob=True,
        )
        value = ValueOperator(_Value(cfg.hidden), in_keys=["hidden"])
    else:
        trunk = SpatialTrunk(cfg, size, pieces).to(memory_format=torch.channels_last)  # type: ignore[call-overload]
        common = TensorDictModule(trunk, in_keys=obs_keys, out_keys=["features", "hidden"])
        head = TensorDictModule(
            SpatialHead(trunk.out_channels, trunk.cells, grid, view, cfg.upsample, pieces),
            in_keys=["features", *mask_keys],
            out_keys=["logits"],
        )
        kwargs: dict = {"window": cfg.mode_window} | ({"pieces": pieces} if pieces else {})
        dist_class: type[GridCategorical] = PieceGridCategorical if pieces else GridCategorical
        logit_keys = ["logits"]
        if grid.refined:
            fine = TensorDictModule(FineHead(trunk.out_channels, grid), in_keys=["features"], out_keys=["fine"])
            head = TensorDictSequential(head, fine)
            logit_keys.append("fine")
            dist_class = CoarseFineCategorical
            # Where the coarse grid's positions fall on the trunk's cells (the fine map's lattice).
            wx, wy = grid_sampling(grid, view, trunk.cells)
            kwargs |= {
                "wx": wx,
                "wy": wy,
                "fine_xy": grid.fine_xy,
                "fine_theta": grid.fine_theta,
            }
        actor = ProbabilisticActor(
            head,
            in_keys=logit_keys,
            out_keys=["action"],
            spec=action_spec,
            distribution_class=dist_class,
            distribution_kwargs=kwargs,
            return_log_prob=True,
        )
        value = ValueOperator(_Value(cfg.hidden), in_keys=["hidden"])
    return ActorValueOperator(common, actor, value)


def compile_networks(actor_critic: ActorValueOperator) -> int:
    """``torch.compile`` the networks inside an actor-critic in place (state-dict keys unchanged);
    the number compiled. On the CPU it fuses the many small elementwise passes around the
    convolutions (about 25 % off a spatial forward and backward, measured), and, for the spatial
    head, the PPO loss's log-probability and entropy over the grid."""
    global _fused_log_prob_entropy
    nets = [m for m in actor_critic.modules() if isinstance(m, _NETWORKS)]
    for m in nets:
        m.compile()
    if any(isinstance(m, SpatialHead) for m in nets) and _fused_log_prob_entropy is None:
        _fused_log_prob_entropy = torch.compile(_log_prob_entropy, dynamic=False)
    return len(nets)


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters())
