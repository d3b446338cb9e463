"""MetaPOCA's learners on RLlib's meta-learning API (its 2.60 bugs: docs/library-facts.md).

``POCADifferentiableLearner`` (a ``TorchDifferentiableLearner``) adapts a parameter dict
to one task: POCA's connectors on the support episodes, POCA's actor and critic losses
through ``torch.func.functional_call``, and ``inner_steps`` full-batch inner steps that are
  * first order (``meta_order=1``, the paper's setting): Adam on detached parameters;
    the meta-gradient is the query loss's gradient at the adapted parameters (FOMAML);
  * second order (``meta_order=2``): SGD keeping the graph (``create_graph=True``), so
    the meta-gradient flows back through every inner step.
``MetaPOCALearner`` (a ``TorchMetaLearner``) adapts per task, takes POCA's loss on each
task's query episodes under the adapted parameters, and makes ``meta_epochs`` meta updates
(Adam) with the task-averaged gradient, re-adapting from the updated weights each time.

RLlib 2.60 bugs worked around (tests cover both):
  1. ``DifferentiableLearnerConfig`` with ``is_multi_agent=True`` reads
     ``rl_module_spec``/``policies``/``policy_mapping_fn``, which it does not define:
     ``MultiAgentDifferentiableLearnerConfig`` adds them.
  2. ``TorchDifferentiableLearner.compute_gradients`` zips every module's parameters with
     the start of the flat gradient list (all modules get module 0's gradients):
     ``compute_gradients`` below walks the gradients with one iterator.
Advantages (support and query) come from the meta critic in a no-grad connector, as in
ProMP-style MAML-PPO; the critic itself is adapted and meta-learned like the actors.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from ray.rllib.connectors.learner import AddOneTsToEpisodesAndTruncate
from ray.rllib.core.learner.differentiable_learner_config import DifferentiableLearnerConfig
from ray.rllib.core.learner.torch.torch_differentiable_learner import (
    TorchDifferentiableLearner,
)
from ray.rllib.core.learner.torch.torch_meta_learner import TorchMetaLearner
from ray.rllib.core.learner.training_data import TrainingData

from rl_scan.algorithms.optim import FusedAdamMixin
from rl_scan.algorithms.poca import columns as C
from rl_scan.algorithms.poca.connectors import AddGroupColumns, POCATargets
from rl_scan.algorithms.poca.learner import actor_loss, value_clip
from rl_scan.algorithms.poca.modules import CRITIC_ID

SUPPORT, QUERY = "support", "query"  # the critic's group tables of a task
ADAM_BETAS, ADAM_EPS = (0.9, 0.999), 1e-8

NamedParams = dict[str, dict[str, torch.Tensor]]


@dataclass
class MultiAgentDifferentiableLearnerConfig(DifferentiableLearnerConfig):
    """Adds what the multi-agent connector pipeline reads (bug 1) and the inner loop's order."""

    rl_module_spec: Any = None
    policies: Any = None
    policy_mapping_fn: Callable | None = None
    meta_order: int = 1


def add_poca_connectors(pipeline, config, *, table_key: str, minibatch_size) -> None:
    """POCA's learner connectors (as ``POCATorchLearner.build``) on another pipeline."""
    team = config.poca_team
    pipeline.prepend(AddGroupColumns(slots=team["slots"], obs_dim=max(team["obs_dims"]),
                                     act_dim=max(team["act_dims"]),
                                     team_reward=team["team_reward"]))
    pipeline.prepend(AddOneTsToEpisodesAndTruncate())
    pipeline.append(POCATargets(gamma=config.gamma, lambda_=config.lambda_,
                                minibatch_size=minibatch_size, table_key=table_key))


def poca_functional_forward(module, params: NamedParams, batch: dict[str, Any],
                            table_key: str, critic_steps: torch.Tensor) -> dict[str, Any]:
    """Forward passes of the actors in ``batch`` and of the critic on ``critic_steps``."""
    out = {mid: torch.func.functional_call(module[mid], params[mid], (batch[mid],))
           for mid in batch}
    out[CRITIC_ID] = torch.func.functional_call(
        module[CRITIC_ID], params[CRITIC_ID],
        ({C.GROUP_ROW: critic_steps, C.TABLE_KEY: table_key},))
    return out


def poca_losses(module, config, fwd_out: dict[str, Any], batch: dict[str, Any],
                table_key: str, critic_steps: torch.Tensor) -> tuple[dict, dict]:
    """POCA's loss per module (actors: clipped policy - beta * entropy; critic: regression)."""
    beta = float(config.entropy_coeff)
    losses, stats = {}, {}
    for mid in batch:
        losses[mid], stats[mid] = actor_loss(fwd_out[mid], batch[mid],
                                             float(config.clip_param), beta)
    critic = module[CRITIC_ID].loss_from_outputs(fwd_out[CRITIC_ID], critic_steps,
                                                 value_clip(config, float(config.clip_param)),
                                                 table_key)
    losses[CRITIC_ID] = critic["critic_loss"]
    stats[CRITIC_ID] = {k: v.detach() for k, v in critic.items()}
    return losses, stats


class POCADifferentiableLearner(TorchDifferentiableLearner):
    """Functional POCA updates of a parameter dict on one task's support episodes."""

    def build(self, device=None) -> None:
        super().build(device=device)
        add_poca_connectors(self._learner_connector, self.config, table_key=SUPPORT,
                            minibatch_size=self.learner_config.minibatch_size)
        self._adam_state: dict[tuple[str, str], dict[str, Any]] = {}

    @property
    def first_order(self) -> bool:
        return self.learner_config.meta_order == 1

    def update(self, params: NamedParams, training_data: TrainingData, **kwargs):
        """Adapt ``params`` to the task (fresh inner-Adam state per adaptation)."""
        self._adam_state = {}
        if self.first_order:
            params = {mid: {n: p.detach().requires_grad_() for n, p in ps.items()}
                      for mid, ps in params.items()}
        return super().update(params=params, training_data=training_data, **kwargs)

    def _make_functional_call(self, params: NamedParams, batch) -> dict[str, Any]:
        # Only modules with rows (the stock call indexes batch[critic]: KeyError).
        self._critic_steps = self.module[CRITIC_ID].minibatches[SUPPORT].next()
        return poca_functional_forward(self.module, params, batch, SUPPORT,
                                       self._critic_steps)

    def compute_losses(self, *, fwd_out: dict[str, Any], batch: dict[str, Any],
                       **kwargs) -> dict[str, Any]:
        losses, stats = poca_losses(self.module, self.config, fwd_out, batch, SUPPORT,
                                    self._critic_steps)
        for mid, s in stats.items():
            self.metrics.log_dict(s, key=mid, window=1)
        return losses

    def compute_loss_for_module(self, *, module_id, config=None, batch, fwd_out):
        raise NotImplementedError("POCA's losses are computed together (compute_losses)")

    def compute_gradients(self, loss_per_module: dict[str, torch.Tensor],
                          params: NamedParams, **kwargs) -> NamedParams:
        """Gradients mapped back to each module's own parameters (bug 2 of 2.60)."""
        flat = [p for ps in params.values() for p in ps.values()]
        keep_graph = not self.first_order
        grads = iter(torch.autograd.grad(sum(loss_per_module.values()), flat,
                                         create_graph=keep_graph, retain_graph=keep_graph,
                                         allow_unused=True))
        return {mid: {name: next(grads) for name in ps} for mid, ps in params.items()}

    def apply_gradients(self, gradients: NamedParams, params: NamedParams) -> NamedParams:
        """First order: an Adam step on detached leaves; second order: a graph-keeping SGD step."""
        lr = self.learner_config.lr
        out: NamedParams = {}
        for mid, ps in params.items():
            out[mid] = {}
            for name, p in ps.items():
                g = gradients[mid][name]
                if g is None:  # a module without rows in this task (e.g. absent kind)
                    out[mid][name] = p
                    continue
                g = torch.nan_to_num(g)
                if self.first_order:
                    step = self._adam_step((mid, name), g.detach(), lr)
                    out[mid][name] = (p.detach() - step).requires_grad_()
                else:
                    out[mid][name] = p - lr * g
        return out

    def _adam_step(self, key: tuple[str, str], g: torch.Tensor, lr: float) -> torch.Tensor:
        state = self._adam_state.setdefault(key, {"t": 0, "m": torch.zeros_like(g),
                                                  "v": torch.zeros_like(g)})
        b1, b2 = ADAM_BETAS
        state["t"] += 1
        state["m"].mul_(b1).add_(g, alpha=1 - b1)
        state["v"].mul_(b2).addcmul_(g, g, value=1 - b2)
        m_hat = state["m"] / (1 - b1 ** state["t"])
        v_hat = state["v"] / (1 - b2 ** state["t"])
        return lr * m_hat / (v_hat.sqrt() + ADAM_EPS)


class MetaPOCALearner(FusedAdamMixin, TorchMetaLearner):
    """Inner adaptation per task, POCA's query loss under the adapted parameters, one
    meta-Adam step over the task batch."""

    def build(self) -> None:
        super().build()
        add_poca_connectors(self._learner_connector, self.config, table_key=QUERY,
                            minibatch_size=None)

    @property
    def inner(self) -> POCADifferentiableLearner:
        return self.others[0]

    def adapt(self, support: list) -> NamedParams:
        """Adapted parameters (detached) for sampling the query episodes of a task."""
        params, _, _ = self.inner.update(params=self._clone_named_parameters(),
                                         training_data=TrainingData(
                                             episodes=copy.deepcopy(support)),
                                         _no_metrics_reduce=True)
        return {mid: {n: p.detach() for n, p in ps.items()} for mid, ps in params.items()}

    def adapted_state(self, params: NamedParams) -> dict[str, dict[str, torch.Tensor]]:
        """Adapted actor weights as module state dicts (to load into env runners)."""
        return {mid: {n: p.detach().clone() for n, p in ps.items()}
                for mid, ps in params.items() if mid != CRITIC_ID}

    def meta_update(self, tasks: list[dict[str, Any]]) -> dict[str, Any]:
        """``config.meta_epochs`` meta steps on one batch of tasks. ``tasks``: dicts with
        ``support`` and ``query`` episodes and, for first order, the ``adapted``
        parameters the query episodes were sampled with.

        Each step adapts every task from the current meta parameters (the first
        first-order step reuses ``adapted``), takes POCA's clipped loss on its query
        episodes under the adapted parameters and makes one meta-Adam step with the
        task-averaged gradient. Several steps per batch of episodes is PPO's reuse of
        its samples (the paper's 3 epochs; RLlib's MAML: ``maml_optimizer_steps``);
        the clipped ratio against the sampling policy keeps the later steps honest.
        """
        if not tasks:
            raise ValueError("meta_update needs at least one task")
        real = {mid: dict(self.module[mid].named_parameters()) for mid in self.module.keys()}
        for epoch in range(int(self.config.meta_epochs)):
            total = {p: torch.zeros_like(p) for ps in real.values() for p in ps.values()}
            query_losses = []
            for task in tasks:
                loss, grads, stats = self._query_gradient(task, real, reuse=epoch == 0)
                for p, g in grads.items():
                    total[p] += g / len(tasks)
                query_losses.append(loss)
                for mid, st in stats.items():
                    self.metrics.log_dict(st, key=mid, window=len(tasks))
            gradients = {self.get_param_ref(p): g for p, g in total.items()}
            self.apply_gradients(self.postprocess_gradients(gradients))
        self.metrics.log_value("meta/query_loss", sum(query_losses) / len(tasks), window=1)
        self.metrics.log_value("meta/grad_norm", math.sqrt(sum(
            float((g * g).sum()) for g in total.values())), window=1)
        return self.metrics.reduce()

    def _query_gradient(self, task: dict[str, Any], real: NamedParams, reuse: bool):
        """(query loss, gradient per real parameter, stats) of one task at the current
        meta parameters ``real``; ``reuse``: first order may take ``task['adapted']``."""
        if self.inner.first_order:
            source = task["adapted"] if reuse else self.adapt(task["support"])
            adapted = {mid: {n: p.detach().clone().requires_grad_() for n, p in ps.items()}
                       for mid, ps in source.items()}
            wrt = adapted  # FOMAML: gradient at the adapted parameters
        else:
            adapted, _, _ = self.inner.update(
                params=self._clone_named_parameters(),
                training_data=TrainingData(episodes=copy.deepcopy(task["support"])),
                _no_metrics_reduce=True)
            wrt = real  # through the inner steps to the meta parameters
        batch = self._learner_connector(rl_module=self.module, batch={},
                                        episodes=copy.deepcopy(task["query"]),
                                        shared_data={}, metrics=self.metrics)
        batch = {mid: b for mid, b in batch.items() if mid in self.module.keys()}
        steps = self.module[CRITIC_ID].minibatches[QUERY].steps
        fwd = poca_functional_forward(self.module, adapted, batch, QUERY, steps)
        losses, stats = poca_losses(self.module, self.config, fwd, batch, QUERY, steps)
        loss = sum(losses.values())
        flat = [(mid, n) for mid, ps in wrt.items() for n in ps]
        grads = torch.autograd.grad(loss, [wrt[mid][n] for mid, n in flat],
                                    allow_unused=True)
        out = {real[mid][n]: g.detach() for (mid, n), g in zip(flat, grads) if g is not None}
        return float(loss.detach()), out, stats
