"""The learner of M members: :class:`ede.method.td3.TD3`'s update on all of them at once.

Each member is the run of one seed: its own random streams (:class:`Streams`), its own networks
and Adam states stacked on a leading axis (:mod:`ede.method.ensemble`), its own batch; what it
computes is what it computes alone (tests/ede/test_group.py holds it bit for bit).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import torch

from ede.config.schema import TD3Config
from ede.method import ensemble
from ede.method.adapters import ActionAdapter
from ede.method.ensemble import Params
from ede.method.nets import matmul_precision, to_device
from ede.method.replay import ReplayBatch, ReplayBuffer
from ede.method.td3 import TD3, Actor, Critic

__all__ = ["PURPOSES", "Agent", "Streams"]


# Each purpose's key in a member's seed sequence: a new purpose takes a new key and shifts none.
PURPOSES = {"weights": 0, "exploration": 1, "target_noise": 2, "replay": 3, "start_codes": 4}


class Streams:
    """One member's random streams: a generator per purpose, each seeded from (seed, purpose)
    by numpy's ``SeedSequence``, so that no stream depends on another member, another purpose,
    or how many of either there are. Initial weights are drawn on the CPU (the same weights on
    every device); the others live on the training device."""

    def __init__(self, seed: int, device: torch.device) -> None:
        for purpose, key in PURPOSES.items():
            state = np.random.SeedSequence(seed, spawn_key=(key,)).generate_state(2, np.uint32)
            where = torch.device("cpu") if purpose == "weights" else device
            generator = torch.Generator(device=where)
            generator.manual_seed(int(state[0]) | int(state[1]) << 32)
            setattr(self, purpose, generator)

    weights: torch.Generator
    exploration: torch.Generator
    target_noise: torch.Generator
    replay: torch.Generator
    start_codes: torch.Generator

    SAVED = ("exploration", "target_noise", "replay", "start_codes")  # what a checkpoint keeps


class Agent:
    """The TD3 learner of M members over any :class:`ActionAdapter` (TD3: identity, EDE-TD3: the
    decoder). A single run is M = 1; member m is the run of seed ``seeds[m]``.

    Its networks and optimiser states hold the members stacked (:mod:`ede.method.ensemble`); an update
    runs :class:`TD3`'s functions on every member at once, each on its own batch and target
    noise drawn from its own generators (:meth:`draw`). Members not due an update keep their
    weights and optimiser states.
    """

    def __init__(
        self,
        obs_size: int,
        adapter: ActionAdapter,
        config: TD3Config,
        device: torch.device,
        seeds: Sequence[int] = (0,),
        fallback: Callable[[str], None] | None = None,
    ) -> None:
        """``config.compile`` says how updates run; "auto" is a run's choice, made from its
        length and the machine (:func:`ede.run.group.compile_mode`), and an agent given it runs
        eager. ``fallback``: where given, an update that fails compiled runs eager instead,
        from then on, and ``fallback`` is told why in one line (a failed compile leaves the
        update's inputs untouched)."""
        self.adapter, self.config, self.device = adapter, config, device
        self.members = len(seeds)
        self.streams = [Streams(seed, device) for seed in seeds]
        actor = Actor(obs_size, adapter.code_low, adapter.code_high, config.hidden)
        critic = Critic(
            obs_size,
            adapter.code_size,
            adapter.k,
            config.hidden,
            adapter.plan_step,
            config.critic_action_repeat,
        )
        self.td3 = TD3(actor, critic, adapter, config)
        # Each member draws its actor's initial weights, then its critic's, from its own stream.
        initial = [(actor.initial(s.weights), critic.initial(s.weights)) for s in self.streams]
        self.actor = ensemble.Stack([a for a, _ in initial], device)
        self.critic = ensemble.Stack([c for _, c in initial], device, networks=2)  # the twins
        self.actor_target, self.critic_target = self.actor.clone(), self.critic.clone()
        self._acting = ensemble.one_row_layers(self.actor.params)  # views of the live weights
        self.actor_adam = ensemble.Adam(self.actor, config.lr)
        self.critic_adam = ensemble.Adam(self.critic, config.lr)
        # Each member's critic steps: the one count of its updates (its actor steps follow).
        self.updates = np.zeros(self.members, dtype=np.int64)
        # Sums per member since the last take_diagnostics(), kept on the device so that no
        # update waits for the host: critic loss, critic steps, actor loss (−mean Q(s, μ(s), 0)),
        # actor steps. A module's buffer, as the networks are (ensemble.Stack says why).
        self._sums = torch.nn.Module()
        self._sums.register_buffer("losses", torch.zeros(4, self.members, device=device))
        self._compiled = config.compile not in ("none", "auto")
        self._update = (
            self._update_eager
            if not self._compiled
            else torch.compile(
                self._update_eager,
                fullgraph=True,
                mode=None if config.compile == "default" else config.compile,
            )
        )
        self._fallback = fallback
        self._ran: set[tuple[bool, bool, bool]] = set()  # the flags of the graphs that ran

    @property
    def compiled(self) -> bool:
        """Whether the updates run compiled (``td3.compile``; False after a fallback)."""
        return self._compiled

    @property
    def loss_sums(self) -> torch.Tensor:
        """``(4, M)``: each member's sums since its last :meth:`take_diagnostics`."""
        return self._sums.get_buffer("losses")

    # Acting, every member at once ----------------------------------------------------------

    @torch.no_grad()
    def act(self, obs: np.ndarray) -> torch.Tensor:
        """μ(s) of every member for its observation, ``(M, O) -> (M, C)``: one forward of the
        stacked actor."""
        x = torch.as_tensor(obs, dtype=torch.float32, device=self.device)[:, None]  # (M, 1, O)
        raw = ensemble.one_row_each(self._acting, x)  # (M, 1, O) -> (M, 1, C)
        return self.td3.actor.squash(raw[:, 0])

    @torch.no_grad()
    def behave(self, obs: np.ndarray, members: np.ndarray, uniform: np.ndarray) -> torch.Tensor:
        """The codes training acts with, ``(M, C)``, for the members of ``members``: uniform in
        the box where ``uniform`` (the start steps), else μ(s) plus exploration noise; every
        draw from the member's own stream (rows of other members: unused)."""
        low, high, scale = self.adapter.code_low, self.adapter.code_high, self.adapter.noise_scale
        draw = self._draw
        if (members & ~uniform).all():  # every member explores: the common case, in one piece
            noise = torch.stack([draw(torch.randn, m, "exploration") for m in range(self.members)])
            return self.td3.clip(self.act(obs) + noise * self.config.exploration_noise * scale)
        codes = low.repeat(len(obs), 1)  # (M, C)
        explore, start = members & ~uniform, members & uniform
        if start.any():
            rows = np.flatnonzero(start)
            u = torch.stack([draw(torch.rand, int(m), "start_codes") for m in rows])
            codes[rows] = low + u * (high - low)
        if explore.any():
            rows = np.flatnonzero(explore)
            noise = torch.stack([draw(torch.randn, int(m), "exploration") for m in rows])
            mean = self.act(obs)[rows]  # (N, C)
            codes[rows] = self.td3.clip(mean + noise * self.config.exploration_noise * scale)
        return codes

    def _draw(self, sample: Callable[..., torch.Tensor], member: int, purpose: str) -> torch.Tensor:
        """One code's worth ``(C,)`` of ``sample`` from member ``member``'s stream ``purpose``."""
        generator = getattr(self.streams[member], purpose)
        return sample(self.adapter.code_size, generator=generator, device=self.device)

    def policy(self, member: int) -> dict[str, torch.Tensor]:
        """Member ``member``'s actor as ``policy.safetensors`` holds it."""
        return self.td3.actor.export(self.actor.member(member))

    # Updating, every member at once ----------------------------------------------------------

    def draw(self, buffer: ReplayBuffer, due: np.ndarray) -> tuple[ReplayBatch, torch.Tensor]:
        """The random part of an update: each due member's batch and target noise, drawn from
        its own generators (members not due draw nothing)."""
        c = self.config
        replay = [s.replay if d else None for s, d in zip(self.streams, due, strict=True)]
        batch = buffer.sample(c.batch_size, replay)
        shape = (c.batch_size, self.adapter.code_size)
        noise = torch.stack(
            [
                torch.randn(shape, generator=s.target_noise, device=self.device)
                if d
                else torch.zeros(shape, device=self.device)
                for s, d in zip(self.streams, due, strict=True)
            ]
        )
        return batch, noise

    def update(self, buffer: ReplayBuffer, due: np.ndarray | None = None) -> None:
        """One TD3 update of the members where ``due`` (``(M,)`` bool; every member by default):
        a critic step, and every ``policy_delay`` of a member's critic steps an actor step and
        target moves. Its matrix products follow ``td3.precision``."""
        due = np.ones(self.members, dtype=bool) if due is None else np.asarray(due, dtype=bool)
        batch, noise = self.draw(buffer, due)
        self.step(batch, noise, due)

    def step(self, batch: ReplayBatch, noise: torch.Tensor, due: np.ndarray) -> None:
        """:meth:`update` on a drawn batch and raw (unit) target noise ``(M, B, C)``."""
        delay = self.config.policy_delay
        actor_due = due & ((self.updates + 1) % delay == 0)
        self.updates += due
        corrections = to_device(  # one copy for both optimisers
            np.stack(
                [
                    self.critic_adam.corrections(self.updates),
                    self.actor_adam.corrections(self.updates // delay),
                ]
            ),
            self.device,
        )
        masks = to_device(np.stack([due, actor_due]), self.device)
        flags = (bool(actor_due.any()), not due.all(), not actor_due.all())
        # Eager, each optimiser's host side (ensemble.Adam.step); compiled, the tensors alone.
        steps = ((self.updates, due), (self.updates // delay, actor_due))
        with matmul_precision(self.config.precision):
            if not self._compiled:
                self._update_eager(batch, noise, masks, corrections, *flags, steps)
                return
            try:
                self._update(batch, noise, masks, corrections, *flags, None)
            except Exception as error:
                # Only a call that compiled a graph (the first of its flags) may fall back: a
                # compile fails before anything runs; a graph that ran and failed may not have.
                if self._fallback is None or flags in self._ran:
                    raise
                self._fallback(
                    f"td3.compile auto: compiling the update failed ({_cause(error)}); it runs eager"
                )
                self._compiled, self._update = False, self._update_eager
                self._update_eager(batch, noise, masks, corrections, *flags, steps)
            self._ran.add(flags)

    def _update_eager(
        self,
        batch: ReplayBatch,
        noise: torch.Tensor,
        masks: torch.Tensor,
        corrections: torch.Tensor,
        actor: bool,
        critic_masked: bool,
        actor_masked: bool,
        steps: tuple[ensemble.Steps, ensemble.Steps] | None = None,
    ) -> None:
        """The update as one function of tensors (no host synchronisation): what
        ``td3.compile`` compiles. ``masks``: ``(2, M)`` bool, the members due a critic step and
        an actor step; ``corrections``: ``(2, 2, M)``, each optimiser's :meth:`Adam.corrections`;
        the flags say, from the host, whether any actor step is due and whether either mask
        leaves a member out; ``steps``: eager, each optimiser's counts and mask on the host
        (:meth:`ensemble.Adam.step`), None where compiled."""
        td3, due, actor_due = self.td3, masks[0], masks[1]
        critic_steps, actor_steps = (None, None) if steps is None else steps
        y = td3.target(self.actor_target.params, self.critic_target.params, batch, noise)
        grad, losses = ensemble.grad(td3.critic_loss, self.critic, batch, y)
        self.critic_adam.step(grad, corrections[0], due if critic_masked else None, critic_steps)
        self.loss_sums[0] += torch.where(due, losses, 0.0)
        self.loss_sums[1] += due
        if not actor:
            return
        grad, losses = ensemble.grad(td3.actor_loss, self.actor, self.critic.params, batch.obs)
        mask = actor_due if actor_masked else None
        self.actor_adam.step(grad, corrections[1], mask, actor_steps)
        self.loss_sums[2] += torch.where(actor_due, losses, 0.0)
        self.loss_sums[3] += actor_due
        self.critic_target.polyak(self.critic, self.config.tau, mask)
        self.actor_target.polyak(self.actor, self.config.tau, mask)

    def take_diagnostics(self, member: int) -> dict[str, float]:
        """Member ``member``'s means over its updates since its last call (one host
        synchronisation), then its sums reset.

        Returns:
            ``updates`` (critic steps), ``critic_loss``, ``actor_loss`` and ``mean_q``, the mean
            of Q_1(s, μ(s), 0) over the actor steps' batches (NaN where there was no step).
        """
        critic, critic_steps, actor, actor_steps = self.loss_sums[:, member].tolist()
        self.loss_sums[:, member] = 0
        nan = float("nan")
        return {
            "updates": int(critic_steps),
            "critic_loss": critic / critic_steps if critic_steps else nan,
            "actor_loss": actor / actor_steps if actor_steps else nan,
            "mean_q": -actor / actor_steps if actor_steps else nan,
        }

    def non_finite(self) -> dict[int, str]:
        """The members whose losses since their last :meth:`take_diagnostics` are not finite
        (one host synchronisation), each with the quantity: the critic's loss, or the actor's
        (minus its Q value)."""
        sums = self.loss_sums
        # Checked after every update: the common case in one operator call, as the sum of
        # everything is finite wherever every term is (a sum that overflows is looked at closely).
        if math.isfinite(sums.sum().item()):
            return {}
        finite = torch.isfinite(sums[0::2]).tolist()  # (2, M): the critic's and the actor's
        names = ("the critic's loss", "the actor's loss (its Q value)")
        return {
            m: names[0] if not finite[0][m] else names[1]
            for m in range(self.members)
            if not (finite[0][m] and finite[1][m])
        }

    # State, one member at a time ---------------------------------------------------------------

    def _member(self, member: int) -> dict[str, Params]:
        """Member ``member``'s networks and optimiser moments (views), by checkpoint prefix."""
        state = {
            "actor": self.actor.member(member),
            "actor_target": self.actor_target.member(member),
            "critic": self.critic.member(member),
            "critic_target": self.critic_target.member(member),
        }
        for name, adam in (("actor_adam", self.actor_adam), ("critic_adam", self.critic_adam)):
            state |= {f"{name}.{moment}": views for moment, views in adam.member(member).items()}
        return state

    def state_dict(self, member: int) -> dict[str, torch.Tensor]:
        """Member ``member``'s learner state, as a run alone holds it (``ede/run/checkpoint.py``):
        each network's parameters (``actor.0.weight``, ``critic.0.weight`` (Q1's and Q2's), ...),
        each optimiser's moments (``actor_adam.exp_avg.0.weight``, ...), its update count,
        diagnostics sums and generator states."""
        state = {
            f"{prefix}.{k}": v
            for prefix, params in self._member(member).items()
            for k, v in params.items()
        }
        state["updates"] = torch.tensor(int(self.updates[member]))
        state["loss_sums"] = self.loss_sums[:, member]
        for purpose in Streams.SAVED:
            state[f"generator.{purpose}"] = getattr(self.streams[member], purpose).get_state()
        return {k: v.detach().cpu().clone() for k, v in state.items()}

    @torch.no_grad()
    def load_state_dict(self, member: int, state: dict[str, torch.Tensor]) -> None:
        """Member ``member`` continues from ``state`` (:meth:`state_dict`'s, from any M)."""
        for prefix, params in self._member(member).items():
            for k, v in params.items():
                v.copy_(state[f"{prefix}.{k}"])
        self.updates[member] = int(state["updates"])
        self.loss_sums[:, member] = state["loss_sums"].to(self.device)
        for purpose in Streams.SAVED:
            getattr(self.streams[member], purpose).set_state(state[f"generator.{purpose}"])


def _cause(error: BaseException) -> str:
    """An error's first line that says something: its own, or its cause's where its own only
    announces another (Dynamo's "backend='inductor' raised:")."""
    for e in (error, error.__cause__):
        lines = [line.strip() for line in str(e or "").splitlines() if line.strip()]
        if lines and not lines[0].endswith("raised:"):
            return lines[0]
    return type(error).__name__
