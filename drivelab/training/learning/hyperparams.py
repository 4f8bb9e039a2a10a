"""Hyperparameters shared by a family of algorithms; each algorithm's ``Params`` extends one.

* :class:`PolicyNetParams`: the policy network of the policy-gradient family (REINFORCE, A2C,
  PPO, GRPO); :class:`ActorCriticParams` adds what A2C and PPO share (rollouts, GAE, the loss weights).
* :class:`OffPolicyParams`: the replay, the targets and the learner of DDPG, TD3 and SAC;
  :class:`NoisyExplorationParams` adds the action noise of DDPG and TD3.

Each ``validate`` raises a one-line :class:`~drivelab.errors.DrivelabError` naming the field.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from drivelab.errors import DrivelabError


@dataclass
class PolicyNetParams:
    """Network hyperparameters of the policy-gradient family (REINFORCE, A2C, PPO, GRPO); each
    algorithm's ``Params`` extends it."""
    hidden: list[int] = field(default_factory=lambda: [64, 64])  # hidden layer widths
    activation: str = "tanh"          # tanh | relu | elu | silu
    log_std_init: float = 0.0     # initial log std of the Gaussian policy (continuous actions)
    # Upper bound on the log std, lowered linearly from log_std_init to this over the run (None:
    # the std is learned freely). The deterministic policy (the mean) is what gets evaluated;
    # when the std stays large, the clipped, noisy actions it was trained with behave differently.
    log_std_final: float | None = None

    def validate(self) -> None:
        if self.log_std_final is not None and self.log_std_final > self.log_std_init:
            raise DrivelabError(f"config field 'log_std_final' ({self.log_std_final}) must be <= "
                                f"'log_std_init' ({self.log_std_init})")


@dataclass
class ActorCriticParams(PolicyNetParams):
    """Hyperparameters that A2C and PPO share (each file sets its own defaults where they differ)."""
    lr: float = 3e-4                  # learning rate (Adam)
    anneal_lr: bool = True        # linear decay to 0 over the run
    num_steps: int = 128          # rollout length T per env
    gamma: float = 0.99               # discount factor
    gae_lambda: float = 0.95          # GAE lambda (1: Monte-Carlo returns, 0: TD(0))
    norm_adv: bool = True         # standardise advantages (per minibatch)
    ent_coef: float = 0.0             # weight of the entropy bonus
    vf_coef: float = 0.5              # weight of the value loss
    max_grad_norm: float = 0.5        # clip the global gradient norm to this
    normalize_obs: bool = False   # running observation normalisation (saved with the weights)
    normalize_reward: bool = False  # divide rewards by the running std of the discounted return
    act_in_workers: bool = False  # each env subprocess plays the rollout with its own copy of the policy (see drivelab/training/collection/worker_rollouts.py)

    def validate(self) -> None:
        super().validate()
        if self.num_steps < 1:
            raise DrivelabError(f"config field 'num_steps' must be >= 1, got {self.num_steps}")
        if not 0 <= self.gae_lambda <= 1 or not 0 <= self.gamma <= 1:
            raise DrivelabError("config fields 'gamma' and 'gae_lambda' must be in [0, 1]")

    def iteration_steps(self, num_envs: int) -> int:
        """Env steps of one iteration (a rollout of ``num_steps`` in each env): ``steps`` is
        rounded up to a multiple of it, so a run ends where its config says."""
        return self.num_steps * num_envs


@dataclass
class OffPolicyParams:
    """Hyperparameters common to DDPG, TD3 and SAC (each adds its own)."""
    buffer_size: int = 1_000_000      # replay buffer capacity (transitions)
    batch_size: int = 256             # transitions per gradient step
    learning_starts: int = 5_000      # random-action heat-up steps before any update
    utd: float = 1.0                  # update-to-data ratio: gradient steps per env step
    gamma: float = 0.99               # discount factor
    n_step: int = 1                   # rewards summed in the TD target (n-step returns; buffers.ReplayBuffer)
    tau: float = 0.005                # Polyak coefficient of the target networks
    actor_lr: float = 3e-4            # actor learning rate (Adam)
    critic_lr: float = 3e-4           # critic (and image encoder) learning rate (Adam)
    hidden: list[int] = field(default_factory=lambda: [256, 256])  # hidden layer widths
    activation: str = "relu"          # tanh | relu | elu | silu
    critic_layer_norm: bool = False   # LayerNorm in the critics' hidden layers (offpolicy_nets.Critics)
    compile: bool = False             # torch.compile the critic and actor forward passes
    # The learner's updates under bfloat16 autocast (precision.update_precision), the output layers
    # kept float32 (precision.in_float32): faster where the CPU has AVX512-BF16 or AMX, and on
    # GPUs; elsewhere torch emulates bfloat16 and the updates run slower (true warns there: Run).
    # auto: bfloat16 where the hardware computes it (precision.native_bf16), float32 elsewhere.
    bf16_updates: bool | str = False
    # The env workers act with a copy of the actor and keep stepping while the learner updates
    # (subprocess envs; see collection.replay.AsyncReplayCollector): faster, with a policy lag.
    act_in_workers: bool = False
    chunk_steps: int = 32             # with act_in_workers: steps each worker plays per weight update
    chunks_in_flight: int = 2         # with act_in_workers: chunks queued in each worker (the lag bound)
    # Prior data (learning.prior_data; RLPD's symmetric sampling), saved in checkpoints.
    prior_data: str | None = None     # a demonstration file (drivelab demos) mixed into every batch
    prior_share: float = 0.5          # the share of each batch's rows drawn from prior_data (RLPD: 0.5)

    def validate(self) -> None:
        if not 0.0 <= self.prior_share < 1.0:
            raise DrivelabError(f"config field 'prior_share' must be in [0, 1), got {self.prior_share}")
        if self.batch_size < 1 or self.buffer_size < self.batch_size:
            raise DrivelabError("config fields 'batch_size' and 'buffer_size' must satisfy 1 <= batch_size <= buffer_size")
        if self.chunk_steps < 1 or self.chunks_in_flight < 1:
            raise DrivelabError("config fields 'chunk_steps' and 'chunks_in_flight' must be >= 1")
        if self.n_step < 1:
            raise DrivelabError(f"config field 'n_step' must be >= 1, got {self.n_step}")
        if self.bf16_updates not in (True, False, "auto"):
            raise DrivelabError(f"config field 'bf16_updates' must be true, false or auto, got {self.bf16_updates!r}")
        if not 0 < self.tau <= 1 or not 0 <= self.gamma <= 1 or self.utd <= 0:
            raise DrivelabError("config fields 'tau' (0, 1], 'gamma' [0, 1] and 'utd' (> 0) are out of range")

    def iteration_steps(self, num_envs: int) -> int:
        """Env steps of one iteration (one step of every env; the workers' last chunks are cut
        to end there): ``steps`` is rounded up to a multiple of it."""
        return num_envs


@dataclass
class NoisyExplorationParams(OffPolicyParams):
    """Exploration by noise on a deterministic actor (DDPG, TD3), with a linear schedule."""
    noise: str = "gaussian"           # gaussian | ou (Ornstein-Uhlenbeck)
    noise_std: float = 0.1            # noise std at the start ...
    noise_std_final: float = 0.1      # ... and after noise_decay_steps
    noise_decay_steps: int = 0
    pre_tanh_l2: float = 0.0          # actor loss + this * mean(u(s)^2), u the actor's pre-tanh output

    def validate(self) -> None:
        super().validate()
        if self.pre_tanh_l2 < 0:
            raise DrivelabError(f"config field 'pre_tanh_l2' must be >= 0, got {self.pre_tanh_l2}")
        if self.noise not in ("gaussian", "ou"):
            raise DrivelabError(f"config field 'noise' must be gaussian or ou, got {self.noise!r}")


LAGRANGE_UPDATES = ("gradient", "pid")


@dataclass
class ConstraintParams:
    """The cost constraint of the Lagrangian algorithms (PPO-Lagrangian, SAC-Lagrangian): keep the
    mean episode cost at or below ``cost_limit``, with a multiplier ``lambda`` on the cost
    (:class:`drivelab.training.learning.lagrange.LagrangeMultiplier`). A mixin: an algorithm's
    ``Params`` lists it after its own base and calls :meth:`validate_constraint`."""
    cost_limit: float = 1.0           # d: the mean episode cost allowed (undiscounted, the env's cost units)
    cost_gamma: float = 0.99          # discount of the cost critic
    lagrange: str = "gradient"        # gradient (projected ascent on lambda) | pid (Stooke et al. 2020)
    lagrange_init: float = 0.0        # lambda at the start
    lagrange_lr: float = 0.05         # gradient: lambda += lagrange_lr * (measured cost - cost_limit)
    lagrange_max: float = 100.0       # lambda is clipped to [0, lagrange_max]
    pid_kp: float = 0.1               # pid: gain on the (smoothed) violation
    pid_ki: float = 0.01              # pid: gain of the integral of the violation
    pid_kd: float = 0.01              # pid: gain on the rise of the (smoothed) cost
    pid_d_delay: int = 10             # pid: the rise is measured against the cost this many updates ago
    pid_ema: float = 0.95             # pid: smoothing of the violation and the cost (0: none)

    def validate_constraint(self, section: str) -> None:
        """One line naming ``section.field`` for a value out of range (``section``: the algorithm)."""
        def number(name: str) -> float:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value \
                    or value in (float("inf"), float("-inf")):
                raise DrivelabError(f"config field '{section}.{name}' must be a finite number, got {value!r}")
            return float(value)

        if number("cost_limit") < 0:
            raise DrivelabError(f"config field '{section}.cost_limit' must be >= 0 (costs are >= 0, so a negative "
                                f"limit can never be met), got {self.cost_limit}")
        if not 0 <= number("cost_gamma") <= 1:
            raise DrivelabError(f"config field '{section}.cost_gamma' must be in [0, 1], got {self.cost_gamma}")
        if self.lagrange not in LAGRANGE_UPDATES:
            raise DrivelabError(f"config field '{section}.lagrange' must be one of {', '.join(LAGRANGE_UPDATES)}, "
                                f"got {self.lagrange!r}")
        if number("lagrange_lr") <= 0 or number("lagrange_max") <= 0:
            raise DrivelabError(f"config fields '{section}.lagrange_lr' and '{section}.lagrange_max' must be > 0")
        if not 0 <= number("lagrange_init") <= self.lagrange_max:
            raise DrivelabError(f"config field '{section}.lagrange_init' must be in [0, lagrange_max], "
                                f"got {self.lagrange_init}")
        if min(number("pid_kp"), number("pid_ki"), number("pid_kd")) < 0:
            raise DrivelabError(f"config fields '{section}.pid_kp', 'pid_ki' and 'pid_kd' must be >= 0")
        if not isinstance(self.pid_d_delay, int) or self.pid_d_delay < 1:
            raise DrivelabError(f"config field '{section}.pid_d_delay' must be an integer >= 1, got {self.pid_d_delay!r}")
        if not 0 <= number("pid_ema") < 1:
            raise DrivelabError(f"config field '{section}.pid_ema' must be in [0, 1), got {self.pid_ema}")
