"""The Effect-Dependent Embedding: encoder E, predictor P (Section 2.2) and decoder D (Section 2.3).

Shapes: B batch, K actions per sequence, A action size, D embedding size, S state size.

* E maps a flattened sequence (B, K·A) to a diagonal Gaussian (mean, log-variance), each (B, D).
* P maps (whitened state (B, S), z (B, D)) to the whitened change of state after K steps (B, S).
* Loss of E and P: mean squared prediction error + β · KL(E(a) ‖ N(0, I)).
* D maps a whitened code (B, D) to K actions inside the action bounds (B, K, A); E is frozen and
  D minimises ‖E(D(z)) − z‖² + λ‖D(z)‖, the minimum-norm one-sided inverse of E (weighted as the
  authors' code weights it: see :func:`train_decoder`).

Codes are *whitened* everywhere outside E: ``z = (mean(E(a)) − μ_z) / σ_z`` with μ_z, σ_z the
moments of E's means over the training windows. This is the space the EDE actor acts in; its bound
is the largest |z| seen there.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ede.config.schema import DecoderConfig, EmbeddingConfig
from ede.io.rollouts import Rollouts, Whitening
from ede.method.nets import initial_weights, mlp

__all__ = [
    "ActionDecoder",
    "ActionEmbedding",
    "DecoderResult",
    "Encoder",
    "EncoderResult",
    "Predictor",
    "gaussian_kl",
    "prediction_loss",
    "split_episodes",
    "train_decoder",
    "train_encoder",
]


class Encoder(nn.Module):
    """E: a k-step action sequence to a diagonal Gaussian over codes."""

    def __init__(self, k: int, action_size: int, dim: int, hidden: list[int]) -> None:
        super().__init__()
        self.k, self.action_size, self.dim = k, action_size, dim
        self.body = mlp(k * action_size, hidden[:-1], hidden[-1], nn.SELU)
        self.mean = nn.Linear(hidden[-1], dim)
        self.log_var = nn.Linear(hidden[-1], dim)

    def forward(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if actions.shape[1:] != (self.k, self.action_size):
            raise ValueError(
                f"expected actions (B, {self.k}, {self.action_size}), found {tuple(actions.shape)}"
            )
        h = F.selu(self.body(actions.flatten(1)))  # (B, K, A) -> (B, K·A) -> (B, H)
        return self.mean(h), self.log_var(h)  # (B, D), (B, D)


class Predictor(nn.Module):
    """P: (whitened state, code) to the whitened k-step change of state."""

    def __init__(self, state_size: int, code_size: int, hidden: list[int]) -> None:
        super().__init__()
        self.net = mlp(state_size + code_size, hidden, state_size, nn.SELU)

    def forward(self, state: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([state, code], dim=-1))  # (B, S + D) -> (B, S)


class ActionDecoder(nn.Module):
    """D: a whitened code to k actions, squashed into the action bounds.

    ``output_range="bounds"`` maps the tanh onto ``[low, high]``; ``"unit"`` keeps it in
    [-1, 1] and clips it to the box, as the authors' code (docs/fidelity.md, row 11a).
    """

    def __init__(
        self,
        dim: int,
        k: int,
        low: np.ndarray,
        high: np.ndarray,
        hidden: list[int],
        output_range: str = "bounds",
    ) -> None:
        super().__init__()
        self.centre: torch.Tensor  # buffers (registered below), saved with the weights
        self.half_range: torch.Tensor
        if output_range not in ("bounds", "unit"):
            raise ValueError(f"output_range {output_range!r}: expected 'bounds' or 'unit'")
        self.k, self.action_size, self.dim, self.output_range = k, len(low), dim, output_range
        self.net = mlp(dim, hidden, k * len(low), nn.SELU)
        self.register_buffer("centre", torch.as_tensor((high + low) / 2, dtype=torch.float32))
        self.register_buffer("half_range", torch.as_tensor((high - low) / 2, dtype=torch.float32))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        unit = torch.tanh(self.net(z)).unflatten(-1, (self.k, self.action_size))  # (B, K, A)
        if self.output_range == "unit":
            return torch.clamp(unit, self.centre - self.half_range, self.centre + self.half_range)
        return self.centre + self.half_range * unit


def gaussian_kl(mean: torch.Tensor, log_var: torch.Tensor) -> torch.Tensor:
    """KL(N(mean, exp(log_var)) ‖ N(0, I)) per sample, summed over dimensions: (B, D) -> (B,)."""
    return 0.5 * (mean.pow(2) + log_var.exp() - 1.0 - log_var).sum(dim=-1)


def prediction_loss(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Squared error averaged over state dimensions, per sample: (B, S) -> (B,).

    Averaging over dimensions (as the authors' code does) keeps β's meaning the same across tasks
    with different state sizes.
    """
    return (predicted - target).pow(2).mean(dim=-1)


def split_episodes(num_episodes: int, holdout: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Episode indices for training and for the held-out split (at least one episode each)."""
    if num_episodes < 2:
        raise ValueError(f"need at least 2 episodes to hold some out, found {num_episodes}")
    order = np.random.default_rng([seed, 7]).permutation(num_episodes)
    held = min(max(1, round(holdout * num_episodes)), num_episodes - 1)
    return np.sort(order[held:]), np.sort(order[:held])


@dataclass
class _Windows:
    """Whitened windows on a device: states (N, S), actions (N, K, A), changes (N, S)."""

    state: torch.Tensor
    actions: torch.Tensor
    delta: torch.Tensor

    def __len__(self) -> int:
        return len(self.state)


def _windows(
    rollouts: Rollouts,
    starts: np.ndarray,
    k: int,
    whitening: tuple[Whitening, Whitening],
    device: torch.device,
    predictor_state: bool = True,
) -> _Windows:
    state, actions, later = rollouts.windows(starts, k)
    state_white, delta_white = whitening

    def tensor(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(x, dtype=torch.float32, device=device)

    seen = state_white.apply(state) if predictor_state else np.zeros_like(state)
    return _Windows(tensor(seen), tensor(actions), tensor(delta_white.apply(later - state)))


def strided(rollouts: Rollouts, starts: np.ndarray, stride: int) -> np.ndarray:
    """The window starts at every ``stride``-th step of their episode (step 0, stride, ...)."""
    return starts[rollouts.t[starts] % stride == 0]


@dataclass
class EncoderResult:
    """A trained E and P with what they were trained on and how well they predict."""

    encoder: Encoder
    predictor: Predictor
    state_whitening: Whitening
    delta_whitening: Whitening
    code_whitening: Whitening  # moments of E's means on the training windows
    history: list[dict[str, float]] = field(default_factory=list)
    metrics: dict[str, float] = field(default_factory=dict)
    train_episodes: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    holdout_episodes: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))


def _batches(n: int, batch_size: int, generator: torch.Generator) -> list[torch.Tensor]:
    order = torch.randperm(n, generator=generator)
    return list(order.split(batch_size))


def train_encoder(
    rollouts: Rollouts,
    config: EmbeddingConfig,
    device: torch.device = torch.device("cpu"),
    on_epoch: Callable[[dict[str, float]], None] | None = None,
) -> EncoderResult:
    """Train E and P on the training episodes; measure them on the held-out ones.

    Alongside, and on the same batches, a *raw* predictor gets the k actions themselves instead of
    a code, with no KL: the held-out gap between the two is what the bottleneck costs.

    Metrics (held-out, whitened units): ``prediction_mse`` of P(s, mean E(a)); ``mean_change_mse``
    of always predicting the training mean change; their ratio ``prediction_ratio``;
    ``raw_prediction_mse`` of the raw predictor; ``kl``, the mean KL per sequence.
    """
    k = config.k
    train_eps, held_eps = split_episodes(rollouts.num_episodes, config.holdout, config.seed)
    train_starts = strided(rollouts, rollouts.window_starts(k, train_eps), config.window_stride)
    held_starts = strided(rollouts, rollouts.window_starts(k, held_eps), config.window_stride)
    if len(train_starts) == 0 or len(held_starts) == 0:
        raise ValueError(f"{rollouts.path}: episodes are too short for windows of k={k}")
    whitening = rollouts.whitening(k, train_starts, config.change_whitening)
    train = _windows(rollouts, train_starts, k, whitening, device, config.predictor_state)
    held = _windows(rollouts, held_starts, k, whitening, device, config.predictor_state)

    generator = torch.Generator().manual_seed(config.seed)
    sample_generator = torch.Generator(device=device).manual_seed(config.seed + 1)
    state_size, action_size = train.state.shape[1], train.actions.shape[2]
    dim = config.dim or action_size
    with initial_weights(config.seed):
        encoder = Encoder(k, action_size, dim, config.hidden).to(device)
        predictor = Predictor(state_size, dim, config.hidden).to(device)
        raw = Predictor(state_size, k * action_size, config.hidden).to(device)
    params = [*encoder.parameters(), *predictor.parameters(), *raw.parameters()]
    optimizer = torch.optim.Adam(params, lr=config.lr, amsgrad=True)

    history = []
    for epoch in range(1, config.epochs + 1):
        totals = torch.zeros(3, device=device)
        for batch in _batches(len(train), config.batch_size, generator):
            state, actions, delta = train.state[batch], train.actions[batch], train.delta[batch]
            mean, log_var = encoder(actions)  # (B, D) each
            noise = torch.randn(mean.shape, generator=sample_generator, device=device)
            z = mean + noise * (0.5 * log_var).exp()  # reparameterised sample of E(a)
            mse = prediction_loss(predictor(state, z), delta).mean()
            kl = gaussian_kl(mean, log_var).mean()
            raw_mse = prediction_loss(raw(state, actions.flatten(1)), delta).mean()
            optimizer.zero_grad(set_to_none=True)
            (mse + config.beta * kl + raw_mse).backward()
            optimizer.step()
            totals += torch.stack([mse.detach(), kl.detach(), raw_mse.detach()]) * len(batch)
        mse, kl, _ = (totals / len(train)).tolist()
        row = {"epoch": epoch, "train_mse": mse, "train_kl": kl, "loss": mse + config.beta * kl}
        row["holdout_mse"] = _holdout_mse(encoder, predictor, held)
        history.append(row)
        if on_epoch is not None:
            on_epoch(row)

    with torch.no_grad():
        codes = torch.cat([encoder(train.actions[b])[0] for b in _chunks(len(train))])
        held_mean, held_log_var = encoder(held.actions)
        baseline = train.delta.mean(dim=0, keepdim=True)  # the training mean change
        metrics = {
            "prediction_mse": _holdout_mse(encoder, predictor, held),
            "mean_change_mse": prediction_loss(baseline.expand_as(held.delta), held.delta)
            .mean()
            .item(),
            "raw_prediction_mse": prediction_loss(
                raw(held.state, held.actions.flatten(1)), held.delta
            )
            .mean()
            .item(),
            "kl": gaussian_kl(held_mean, held_log_var).mean().item(),
        }
    metrics["prediction_ratio"] = metrics["prediction_mse"] / metrics["mean_change_mse"]
    metrics["raw_prediction_ratio"] = metrics["raw_prediction_mse"] / metrics["mean_change_mse"]
    return EncoderResult(
        encoder=encoder.eval(),
        predictor=predictor.eval(),
        state_whitening=whitening[0],
        delta_whitening=whitening[1],
        code_whitening=Whitening.of(codes.cpu().double().numpy()),
        history=history,
        metrics=metrics,
        train_episodes=train_eps,
        holdout_episodes=held_eps,
    )


def _chunks(n: int, size: int = 8192) -> list[slice]:
    return [slice(i, min(i + size, n)) for i in range(0, n, size)]


@torch.no_grad()
def _holdout_mse(encoder: Encoder, predictor: Predictor, held: _Windows) -> float:
    mean, _ = encoder(held.actions)
    return prediction_loss(predictor(held.state, mean), held.delta).mean().item()


@dataclass
class DecoderResult:
    """A trained D, the bound of the actor's codes, and how well D inverts E."""

    decoder: ActionDecoder
    bound: float
    history: list[dict[str, float]] = field(default_factory=list)
    metrics: dict[str, float] = field(default_factory=dict)


class ActionEmbedding(nn.Module):
    """E and D behind one face: ``encode(actions) -> z`` and ``decode(z) -> actions``, batched.

    ``z`` is always the whitened code, the EDE actor's action space, bounded by ``bound``. Without
    its encoder (a published decoder alone, :func:`ede.run.artifacts.load_action_embedding`) it
    decodes, which is all a trained policy needs to act, and encodes nothing.
    """

    def __init__(
        self,
        encoder: Encoder | None,
        decoder: ActionDecoder,
        code_whitening: Whitening,
        bound: float,
    ):
        super().__init__()
        self.code_mean: torch.Tensor  # buffers (registered below)
        self.code_std: torch.Tensor
        self.encoder = None if encoder is None else encoder.eval()
        self.decoder = decoder.eval()
        self.k, self.action_size, self.dim = decoder.k, decoder.action_size, decoder.dim
        self.bound = float(bound)
        self.register_buffer("code_mean", torch.as_tensor(code_whitening.mean, dtype=torch.float32))
        self.register_buffer("code_std", torch.as_tensor(code_whitening.std, dtype=torch.float32))
        for p in self.parameters():
            p.requires_grad_(False)

    def encode(self, actions: torch.Tensor) -> torch.Tensor:
        """Whitened codes of action sequences: (B, K, A) -> (B, D)."""
        if self.encoder is None:
            raise ValueError("this embedding was loaded without its encoder: it only decodes")
        mean, _ = self.encoder(actions)
        return (mean - self.code_mean) / self.code_std

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Action sequences of whitened codes: (B, D) -> (B, K, A), inside the action bounds."""
        if z.shape[-1] != self.dim:
            raise ValueError(f"expected codes (B, {self.dim}), found {tuple(z.shape)}")
        return self.decoder(z)

    @property
    def device(self) -> torch.device:
        return self.code_mean.device


def train_decoder(
    rollouts: Rollouts,
    encoded: EncoderResult,
    config: DecoderConfig,
    k: int,
    low: np.ndarray,
    high: np.ndarray,
    device: torch.device = torch.device("cpu"),
    on_epoch: Callable[[dict[str, float]], None] | None = None,
) -> DecoderResult:
    """Train D against the frozen E: ‖E(D(z)) − z‖² + λ‖D(z)‖ (Section 2.3).

    The terms are weighted as in the authors' code, where the paper's λ = 1e-4 was tuned: the
    reconstruction error is the mean over batch and code dimensions, the norm the *sum* over the
    batch and the k steps of each action's Euclidean norm. Taken per sample as the paper's formula
    reads, λ = 1e-4 is about a hundred times weaker, and D is then no minimum-norm inverse at all
    (measured: D(E(0)) decoded to actions as large as random ones, and EDE-TD3 on ReacherVertical
    stayed at a random policy's return).

    Training codes come from ``config.z_source``: ``"marginal"`` draws the whitened codes of the
    training windows (the authors' code), ``"prior"`` draws z ~ N(0, I) in the whitened space. An
    epoch is as many batches as the training windows fill. Metrics, on the held-out windows'
    codes: ``inverse_error`` = mean ‖E(D(z)) − z‖² / mean ‖z − z̄‖², and ``at_bounds`` = the
    fraction of decoded action components within 1% of the range of a bound.
    """
    encoder = encoded.encoder.to(device)
    for p in encoder.parameters():
        p.requires_grad_(False)
    embedding_whitening = encoded.code_whitening
    with initial_weights(config.seed):
        decoder = ActionDecoder(encoder.dim, k, low, high, config.hidden, config.output_range).to(
            device
        )
    code_mean = torch.as_tensor(embedding_whitening.mean, dtype=torch.float32, device=device)
    code_std = torch.as_tensor(embedding_whitening.std, dtype=torch.float32, device=device)

    def whitened_codes(starts: np.ndarray) -> torch.Tensor:
        _, actions, _ = rollouts.windows(starts, k)
        actions_t = torch.as_tensor(actions, dtype=torch.float32, device=device)
        with torch.no_grad():
            means = torch.cat([encoder(actions_t[c])[0] for c in _chunks(len(actions_t))])
        return (means - code_mean) / code_std

    train_z = whitened_codes(rollouts.window_starts(k, encoded.train_episodes))
    held_z = whitened_codes(rollouts.window_starts(k, encoded.holdout_episodes))
    bound = train_z.abs().max().item()

    generator = torch.Generator().manual_seed(config.seed)
    prior_generator = torch.Generator(device=device).manual_seed(config.seed + 1)
    optimizer = torch.optim.Adam(decoder.parameters(), lr=config.lr)
    history = []
    for epoch in range(1, config.epochs + 1):
        totals = torch.zeros(2, device=device)
        for batch in _batches(len(train_z), config.batch_size, generator):
            if config.z_source == "marginal":
                z = train_z[batch]
            else:
                z = torch.randn((len(batch), encoder.dim), generator=prior_generator, device=device)
            actions = decoder(z)  # (B, D) -> (B, K, A)
            recon = ((encoder(actions)[0] - code_mean) / code_std - z).pow(2).mean()
            norm = actions.norm(dim=-1).sum()  # (B, K, A) -> summed over B and K
            optimizer.zero_grad(set_to_none=True)
            (recon + config.lam * norm).backward()
            optimizer.step()
            totals += torch.stack([recon.detach(), norm.detach()]) * len(batch)
        recon_mean, norm_mean = (totals / len(train_z)).tolist()
        row = {"epoch": epoch, "recon": recon_mean, "norm": norm_mean}
        row["loss"] = recon_mean + config.lam * norm_mean
        row["holdout_inverse_error"] = _inverse_error(encoder, decoder, held_z, code_mean, code_std)
        history.append(row)
        if on_epoch is not None:
            on_epoch(row)

    with torch.no_grad():
        decoded = decoder(held_z)
        span = decoder.half_range * 2
        near = torch.minimum(
            decoded - (decoder.centre - decoder.half_range),
            (decoder.centre + decoder.half_range) - decoded,
        )
        at_bounds = (near <= 0.01 * span).float().mean().item()
    metrics = {
        "inverse_error": _inverse_error(encoder, decoder, held_z, code_mean, code_std),
        "at_bounds": at_bounds,
        "bound": bound,
    }
    return DecoderResult(decoder=decoder.eval(), bound=bound, history=history, metrics=metrics)


@torch.no_grad()
def _inverse_error(
    encoder: Encoder,
    decoder: ActionDecoder,
    z: torch.Tensor,
    code_mean: torch.Tensor,
    code_std: torch.Tensor,
) -> float:
    recoded = (encoder(decoder(z))[0] - code_mean) / code_std
    spread = (z - z.mean(dim=0, keepdim=True)).pow(2).sum(dim=-1).mean()
    return ((recoded - z).pow(2).sum(dim=-1).mean() / spread).item()
