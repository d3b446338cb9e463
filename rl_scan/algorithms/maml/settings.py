"""MetaPOCA's own settings (the paper's Algorithm 1), kept out of the generic training preset."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from rl_scan.config import check_range, fail
from rl_scan.envs.sim.scenarios import N_TRAIN

OUTER_RULES = ("maml", "maml_dr", "reptile", "multitask")
INNER_ADAM = ("fresh", "meta", "scale")
SAMPLING = ("per_task", "shared")
MAML_STEPS = ("per_task", "mean")


@dataclass(frozen=True)
class MetaSettings:
    """Meta-learning settings of one MetaPOCA run.

    Paper: tau = 10 tasks, K = 20 support and 20 query episodes per task (500 steps each:
    10,000 env steps), an inner update of POCA's 3 epochs.
    """

    tasks: int = 10
    """Tasks (distinct train scenarios) per meta-iteration (paper tau = 10)."""
    support_steps: int = 10_000
    """Env steps sampled per task with the meta policy (paper: K = 20 episodes of 500)."""
    query_steps: int = 10_000
    """Env steps sampled per task with the adapted policy."""
    inner_updates: int = 1
    """Ordinary POCA updates (the preset's epochs and minibatches) on the support batch."""
    inner_lr: float = 1.0
    """The inner updates' lr as a multiple of POCA's (MAML's alpha over beta): one update at
    POCA's lr moves the policy about one training iteration's worth, too little for a
    scene to show in the adapted policy's coverage (docs/DESIGN.md, #16)."""
    inner_adam: str = "fresh"
    """The inner update's Adam state: ``fresh`` (a new optimizer, the paper's reading),
    ``meta`` (a copy of the meta optimizer's moments: the inner steps continue its
    momentum) or ``scale`` (its second moment only: the task's gradient direction at the
    meta optimizer's per-weight scale; ``learners.inner_adam_state``)."""
    outer: str = "maml"
    """``maml``: first-order MAML-PPO on support (at theta) and query (at theta + delta)
    batches; ``maml_dr``: the same with the update at theta on every batch (DR's update
    on all the data plus the MAML term); ``reptile``: theta += reptile_lr * mean over
    tasks of delta; ``multitask`` (a control): one update at theta on all batches, tasks
    mixed: DR on the same data."""
    reptile_lr: float = 1.0
    """Reptile's step size epsilon (only with ``outer="reptile"``)."""
    maml_weight: float = 1.0
    """The MAML term's step size as a fraction of POCA's lr (``maml``, ``maml_dr``): the
    per-task query updates at theta + delta run with lr x maml_weight (with Adam the
    length of their steps); 0 leaves only the update at theta."""
    maml_step: str = "per_task"
    """How the MAML term (``maml``, ``maml_dr``) steps: ``per_task``, each task's query
    update at theta + delta_i takes its own meta-Adam steps (one per minibatch), so the
    term makes tasks x epochs x minibatches steps, each on one task's query; ``mean``, one
    meta-Adam step per (epoch, minibatch) on the mean over tasks of their gradients at
    theta + delta_i, the paper's meta-gradient (``MetaPOCALearner.mean_shifted_update``)."""
    relabel_query: bool = False
    """The update at theta (``maml_dr``, ``multitask``) takes the query episodes, sampled by
    the adapted actors theta'_i, as if theta had sampled them (its PPO ratio starts at 1
    on them). Without it the ratio starts at pi_theta / pi_theta'_i, one inner update away
    from 1, and PPO's clip drops many query rows' gradient from the first minibatch on."""
    query_importance: bool = False
    """With ``relabel_query``: each query row of the update at theta is weighed by
    pi_theta / pi_theta'_i of its action (capped at 2; ``poca.losses.importance_weights``),
    the decoupled PPO objective: the ratio is clipped around theta and the weight makes the
    surrogate an expectation under theta although theta'_i sampled the rows. Without it
    the relabelled rows pull theta towards the actions theta'_i prefers."""
    sampling: str = "per_task"
    """``per_task``: every task samples its support (theta) and query (theta'_i) batches
    from fresh episodes of its scene on the runner's envs. ``shared``: the runner samples
    ``support_steps`` with theta exactly as DR does (``train:*``, episodes continued across
    meta-iterations) and the update at theta learns from all of it; the tasks are ``tasks``
    of the whole episodes in that batch (a scene each), and each task's query
    (``query_steps`` from a fresh episode of its scene, theta'_i) runs on a one-env side
    runner. A meta-iteration then costs support_steps + tasks x query_steps env steps."""
    task_envs: int = 0
    """Envs (worlds) the runner samples each task's batches on, in place of the preset's
    ``num_envs_per_env_runner`` (0: the preset's). One env lets a 4k meta-iteration hold
    4 tasks of one support and one query episode each."""

    def validate(self, prefix: str = "") -> None:
        check_range(prefix + "tasks", self.tasks, 1, N_TRAIN)  # distinct train scenarios
        check_range(prefix + "support_steps", self.support_steps, 1)
        check_range(prefix + "query_steps", self.query_steps, 1)
        check_range(prefix + "inner_updates", self.inner_updates, 1, 100)
        check_range(prefix + "inner_lr", self.inner_lr, 0.0, 100.0, lo_open=True)
        if self.inner_adam not in INNER_ADAM:
            fail(prefix + "inner_adam", self.inner_adam, f"one of {list(INNER_ADAM)}")
        if self.outer not in OUTER_RULES:
            fail(prefix + "outer", self.outer, f"one of {list(OUTER_RULES)}")
        check_range(prefix + "reptile_lr", self.reptile_lr, 0.0, 1.0, lo_open=True)
        check_range(prefix + "maml_weight", self.maml_weight, 0.0, 10.0)
        check_range(prefix + "task_envs", self.task_envs, 0, 256)
        if self.maml_step not in MAML_STEPS:
            fail(prefix + "maml_step", self.maml_step, f"one of {list(MAML_STEPS)}")
        if self.maml_step == "mean" and self.outer not in ("maml", "maml_dr"):
            fail(prefix + "maml_step", self.maml_step,
                 f"'per_task' with outer={self.outer!r} (it shapes the MAML term, which "
                 "only 'maml' and 'maml_dr' take)")
        if self.sampling not in SAMPLING:
            fail(prefix + "sampling", self.sampling, f"one of {list(SAMPLING)}")
        if self.relabel_query and self.outer not in ("maml_dr", "multitask"):
            fail(prefix + "relabel_query", self.relabel_query,
                 f"false with outer={self.outer!r} (it relabels the query batches of the "
                 "update at theta, which only 'maml_dr' and 'multitask' make)")
        if self.query_importance and not self.relabel_query:
            fail(prefix + "query_importance", self.query_importance,
                 "false unless relabel_query=true (the weight corrects the relabelled "
                 "query rows; without the relabel the ratio already has theta'_i below it)")

    def fit_preset(self, preset, prefix: str = ""):
        """The training preset as a MetaPOCA run uses it: support and query steps that fill
        the runner's envs, a budget of whole meta-iterations (no method trains past it),
        and evaluations and checkpoints at the preset's env-step spacing (on ``task_envs``
        envs per runner if set)."""
        if self.task_envs:
            preset = dataclasses.replace(preset, num_envs_per_env_runner=self.task_envs)
        self.check_steps_fit(preset.num_envs_per_env_runner, prefix)
        per_iteration = self.env_steps_per_iteration()
        if preset.total_env_steps % per_iteration:
            fail("total_env_steps", preset.total_env_steps,
                 f"a multiple of {per_iteration:,}, MetaPOCA's env steps per meta-iteration "
                 "(tasks x (support_steps + query_steps)), so that every method gets the "
                 "same budget")
        return dataclasses.replace(preset, **{
            name: max(1, round(getattr(preset, name) * preset.train_batch_size / per_iteration))
            for name in ("evaluation_interval", "checkpoint_frequency")
            if getattr(preset, name) > 0})

    def env_steps_per_iteration(self) -> int:
        if self.sampling == "shared":
            return self.support_steps + self.tasks * self.query_steps
        return self.tasks * (self.support_steps + self.query_steps)

    def check_steps_fit(self, envs: int, prefix: str = "", max_steps: int = 0) -> None:
        """Batches the runner's ``envs`` sample whole: support (and, per task, query) steps
        a multiple of the envs that sample them (every env steps alike, nothing sampled is
        discarded); with ``max_steps`` (the episode length), batches long enough for whole
        episodes."""
        runner = f"num_envs_per_env_runner={envs}"
        samplers = {"support_steps": (envs, runner),
                    "query_steps": ((1, "the side runner's 1 env") if self.sampling == "shared"
                                    else (envs, runner))}
        for name, (n, label) in samplers.items():
            steps = getattr(self, name)
            if steps < n or steps % n:
                fail(prefix + name, steps, f"a multiple of {label} (every env steps alike; "
                                           "nothing is discarded)")
        if not max_steps:
            return
        if self.sampling == "shared":
            if self.support_steps // envs < 2 * max_steps:
                fail(prefix + "support_steps", self.support_steps,
                     f"at least 2 x max_steps x {runner} = {2 * max_steps * envs} with "
                     "sampling='shared' (episodes continue across meta-iterations: each env "
                     "then holds a whole episode for a task in every batch)")
            if self.tasks > envs:
                fail(prefix + "tasks", self.tasks, f"at most {runner} with sampling='shared' "
                                                   "(the batch's whole episodes are the tasks)")
        fresh = {name: sampler for name, sampler in samplers.items()  # shared: support
                 if not (name == "support_steps" and self.sampling == "shared")}  # continues
        for name, (n, label) in fresh.items():  # these samples start fresh episodes
            steps = getattr(self, name)
            if steps // n < max_steps:
                fail(prefix + name, steps, f"at least max_steps x {label} = {max_steps * n} "
                                           "(each sample starts fresh episodes: fewer steps "
                                           "per env would cut every episode short)")


# Smaller task batches for the short presets (the defaults are the paper's: 200k env steps
# per meta-iteration). Each divides its presets' budgets (smoke 800, quick 100k-1M).
# quick: 4 tasks of one episode each for support and query on one env = 4k env steps,
# DR's batch, with the DR update on all of it (maml_dr) and inner steps that continue the
# meta Adam. Several scenes per update: a critic that learns from one scene per update,
# another each time, does not learn (docs/DESIGN.md, #16).
PRESET_SETTINGS = {"smoke": dict(tasks=2, support_steps=100, query_steps=100),
                   "quick": dict(tasks=4, support_steps=500, query_steps=500, task_envs=1,
                                 outer="maml_dr", inner_adam="meta")}
