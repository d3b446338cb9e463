"""MetaPOCA's learner: POCA's own learner plus the three moves first-order MAML-PPO needs.

``adapt``       the inner loop: ordinary POCA updates (this learner's ``update``: the
                preset's epochs and minibatches, Adam at POCA's lr (times a factor: MAML's
                alpha) from a fresh state,
                actors and critic) on one task's support batch. It returns the task's
                delta = theta' - theta and the adapted actors, and puts the learner back
                at theta with its meta optimizer state.
``shifted``     the parameters moved to theta + delta for a block: an optimizer step taken
                inside applies the loss gradient at theta + delta to theta, which is the
                first-order MAML gradient (d L(theta + delta) / d theta with delta held
                constant: what ``torch.func.functional_call`` at theta + delta gives),
                with no second copy of the modules.
``lr_scaled``   every optimizer's lr times a factor for a block (the MAML term's weight).
``mean_shifted_update`` the MAML term with one meta-Adam step per minibatch on the mean
                over tasks of the gradients at theta + delta_i (the paper's meta-gradient).
``critic_frozen`` updates inside a block leave the critic as it is (the per-task updates
                at theta + delta: the critic learns where the tasks are mixed).
``reptile_step`` theta += epsilon * mean over tasks of delta.
``relabel_behaviour`` episodes sampled by an adapted policy are clipped around theta (the
                PPO ratio's denominator becomes theta's action distribution; the stored
                log-probability stays the sampler's, for the importance weight).

Return statistics (the critic's PopArt moments) belong to the meta-learner: the outer
update at theta moves them; inside ``shifted`` they are frozen, so the adapted critic's
outputs are read in the meta statistics' units.
"""

from __future__ import annotations

import copy
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch
from ray.rllib.core.columns import Columns
from ray.rllib.core.learner.training_data import TrainingData
from ray.rllib.utils.minibatch_utils import MiniBatchCyclicIterator

from rl_scan.algorithms.poca.learner import POCATorchLearner
from rl_scan.algorithms.poca.modules import CRITIC_ID

Key = tuple[str, str]  # (module id, parameter or buffer name)


def inner_adam_state(optimizer: torch.optim.Adam, mode: str) -> None:
    """In place, the Adam state an inner update starts from (``_restore`` puts the meta
    state and hyperparameters back afterwards).

    ``fresh``  no moments: the first steps move every weight by about lr (m / sqrt(v) ~
               sign(g)), whatever the gradient's size;
    ``meta``   the meta optimizer's moments as they are: the steps continue its momentum,
               so every task's step leans the same way;
    ``scale``  the meta optimizer's second moment and step count only, first moment
               zeroed and beta1 = 0: a step is lr * g / sqrt(v_meta), the task's own
               gradient direction at the scale the meta optimizer has learnt per weight.
    """
    if mode == "fresh":
        optimizer.state.clear()
    elif mode == "scale":
        for group in optimizer.param_groups:
            group["betas"] = (0.0, group["betas"][1])
        for state in optimizer.state.values():
            if "exp_avg" in state:
                state["exp_avg"].zero_()
    elif mode != "meta":
        raise ValueError(f"inner Adam mode {mode!r}: allowed fresh, meta, scale")


class MetaPOCALearner(POCATorchLearner):
    """POCA's learner with ``adapt``, ``shifted`` and ``reptile_step`` (see the module doc)."""

    def update_kwargs(self, timesteps: dict[str, Any]) -> dict[str, Any]:
        """The keywords of one ordinary POCA update (as PPO's training step passes them)."""
        cfg = self.config
        return dict(timesteps=timesteps, num_epochs=cfg.num_epochs,
                    minibatch_size=cfg.minibatch_size,
                    shuffle_batch_per_epoch=cfg.shuffle_batch_per_epoch)

    def float_state(self) -> dict[Key, torch.Tensor]:
        """Every parameter and floating-point buffer (the return moments), by key."""
        return {(mid, name): t for mid in self.module.keys()
                for name, t in self.module[mid].state_dict(keep_vars=True).items()
                if t.is_floating_point()}

    def adapt(self, episodes: list, timesteps: dict[str, Any], updates: int = 1,
              start: dict[Key, torch.Tensor] | None = None, adam: str = "fresh",
              lr_scale: float = 1.0
              ) -> tuple[dict[Key, torch.Tensor], dict[str, dict[str, torch.Tensor]], dict]:
        """``updates`` ordinary POCA updates on ``episodes`` from theta (or theta + ``start``)
        at POCA's lr x ``lr_scale``, with the Adam state ``adam`` names
        (``inner_adam_state``: fresh, a copy of the meta Adam's, or its scale only).

        Returns (delta = the state reached - theta, the adapted actors' state dicts, the
        last update's results); the learner is back at theta, its optimizer state the
        meta one.
        """
        saved = self._snapshot()
        theta = {(mid, name): t for mid, state in saved[0].items() for name, t in state.items()
                 if t.is_floating_point()}
        if start is not None:
            with torch.no_grad():
                for key, t in self.float_state().items():
                    t.add_(start[key])
        for optimizer in self._named_optimizers.values():
            inner_adam_state(optimizer, adam)
        for _ in range(updates):
            with self.lr_scaled(lr_scale):  # per update: RLlib resets the lr after each
                results = self.update(episodes=copy.deepcopy(episodes),
                                      **self.update_kwargs(timesteps))
        delta = {k: t.detach() - theta[k] for k, t in self.float_state().items()}
        adapted = {mid: {n: t.detach().clone() for n, t in self.module[mid].state_dict().items()}
                   for mid in self.module.keys() if mid != CRITIC_ID}
        self._restore(saved)
        return delta, adapted, results

    @contextmanager
    def shifted(self, delta: dict[Key, torch.Tensor]) -> Iterator[None]:
        """Parameters at theta + delta inside the block (return statistics frozen)."""
        params = {(mid, name): p for mid in self.module.keys()
                  for name, p in self.module[mid].named_parameters()}
        critic = self.module[CRITIC_ID]
        with torch.no_grad():
            for key, p in params.items():
                p.add_(delta[key])
        critic.return_stats_frozen = True
        try:
            yield
        finally:
            critic.return_stats_frozen = False
            with torch.no_grad():
                for key, p in params.items():
                    p.sub_(delta[key])

    def mean_shifted_update(self, tasks: list[tuple[list, dict[Key, torch.Tensor]]], *,
                            timesteps: dict[str, Any], num_epochs: int, minibatch_size: int,
                            shuffle_batch_per_epoch: bool) -> dict:
        """The MAML term as the paper's meta-gradient: per (epoch, minibatch) one meta-Adam
        step at theta with the mean over tasks of the query loss's gradient at
        theta + delta_i (``tasks``: (query episodes, delta_i) pairs of equal size; actors
        only, the critic frozen). Each task's batch (advantages from its adapted critic) is
        built once at theta + delta_i."""
        self.before_gradient_based_update(timesteps=timesteps)
        iterators = []
        with self.critic_frozen():
            for episodes, delta in tasks:
                with self.shifted(delta):
                    batch = self._make_batch_if_necessary(TrainingData(episodes=episodes))
                iterators.append(MiniBatchCyclicIterator(
                    self._set_slicing_by_batch_id(batch, value=True), num_epochs=num_epochs,
                    minibatch_size=minibatch_size,
                    shuffle_batch_per_epoch=shuffle_batch_per_epoch and num_epochs > 1))
            for minibatches in zip(*iterators, strict=True):
                gradients = []
                for (_, delta), minibatch in zip(tasks, minibatches):
                    with self.shifted(delta):
                        fwd_out = self.module.forward_train(minibatch.policy_batches)
                        losses = self.compute_losses(fwd_out=fwd_out,
                                                     batch=minibatch.policy_batches)
                        gradients.append({ref: g.detach().clone() for ref, g in
                                          self.compute_gradients(losses).items()
                                          if g is not None})  # the critic's are None
                    self._log_steps_trained_metrics(minibatch)
                    self._set_slicing_by_batch_id(minibatch, value=False)
                mean = {ref: torch.stack([g[ref] for g in gradients]).mean(dim=0)
                        for ref in gradients[0]}
                self.apply_gradients(self.postprocess_gradients(mean))
        self.after_gradient_based_update(timesteps=timesteps)
        return self.metrics.reduce()

    @contextmanager
    def critic_frozen(self) -> Iterator[None]:
        """Updates inside the block train the actors only: the critic's loss is left out,
        so it gets no gradient and its Adam takes no step (its moments stay as well)."""
        self.critic_learns = False
        try:
            yield
        finally:
            self.critic_learns = True

    @contextmanager
    def lr_scaled(self, factor: float) -> Iterator[None]:
        """Every optimizer's lr times ``factor`` inside the block (RLlib sets the lr back
        from its schedule after each update; the block's end restores it as well)."""
        optimizers = list(self._named_optimizers.values())
        saved = [self._get_optimizer_lr(opt) for opt in optimizers]
        for opt, lr in zip(optimizers, saved):
            self._set_optimizer_lr(opt, lr * factor)
        try:
            yield
        finally:
            for opt, lr in zip(optimizers, saved):
                self._set_optimizer_lr(opt, lr)

    @torch.no_grad()
    def reptile_step(self, deltas: list[dict[Key, torch.Tensor]], epsilon: float) -> None:
        """theta += epsilon * mean_i delta_i (parameters and return moments alike)."""
        for key, t in self.float_state().items():
            t.add_(epsilon * torch.stack([d[key] for d in deltas]).mean(dim=0))
        critic = self.module[CRITIC_ID]
        if critic.normalize_returns:
            critic.return_stats_set.fill_(True)  # the tasks' moments, averaged, are set

    @torch.no_grad()
    def relabel_behaviour(self, episodes: list) -> None:
        """In place: every agent step's stored action distribution becomes the current
        actors' (theta's). An update at theta then clips its ratio around theta on batches
        the adapted actors theta'_i sampled: the ratio starts at 1 on every row instead of
        at pi_theta / pi_theta'. The stored log-probability stays the sampling policy's
        (theta'_i's), so the loss can weigh each row by pi_theta / pi_theta'_i
        (``query_importance``); without that weight the relabel is a bias of one inner
        update's size."""
        for episode in episodes:
            for agent_id, steps in episode.agent_episodes.items():
                n = len(steps)
                if n == 0:
                    continue
                obs = torch.as_tensor(np.asarray(steps.get_observations(slice(0, n))),
                                      dtype=torch.float32)
                module = self.module[episode.module_for(agent_id)]
                inputs = module._forward({Columns.OBS: obs})[Columns.ACTION_DIST_INPUTS]
                steps.set_extra_model_outputs(key=Columns.ACTION_DIST_INPUTS,
                                              new_data=inputs.numpy(), at_indices=slice(0, n))

    def _snapshot(self) -> tuple[dict, dict]:
        modules = {mid: copy.deepcopy(self.module[mid].state_dict())
                   for mid in self.module.keys()}
        optimizers = {name: copy.deepcopy(opt.state_dict())
                      for name, opt in self._named_optimizers.items()}
        return modules, optimizers

    def _restore(self, saved: tuple[dict, dict]) -> None:
        modules, optimizers = saved
        for mid, state in modules.items():
            self.module[mid].load_state_dict(state)  # in place: optimizers keep their tensors
        for name, state in optimizers.items():
            self._named_optimizers[name].load_state_dict(state)
