"""POCA's math as pure functions (numpy / torch), unit-tested against hand-computed values.

Follows ML-Agents' MA-POCA (``trainers/poca``): lambda-returns of the group reward
bootstrapped from the centralized value V, advantage = return - counterfactual baseline,
PPO clipping per action dimension, and value/baseline regression with clipping around
the old predictions (``trust_region_value_loss``).
"""

from __future__ import annotations

import math

import numpy as np
import torch

LOG_2PI = math.log(2.0 * math.pi)


def lambda_returns(values: np.ndarray, rewards: np.ndarray, terminateds: np.ndarray,
                   truncateds: np.ndarray, gamma: float, lambda_: float) -> np.ndarray:
    """TD(lambda) returns G_t = r_t + gamma * ((1 - lambda) V_{t+1} + lambda G_{t+1}).

    The inputs are concatenated episode chunks, each followed by one extra bootstrap row
    (RLlib's ``AddOneTsToEpisodesAndTruncate``). On the last real row of a chunk,
    ``terminateds`` means no next state (G = r) and ``truncateds`` means the chunk was cut
    and the bootstrap row's value continues it (G = r + gamma V_boot). Bootstrap rows get
    G = V; they are masked out of every loss.
    """
    values = np.asarray(values, dtype=np.float64)
    rewards = np.asarray(rewards, dtype=np.float64)
    n = len(values)
    out = np.zeros(n)
    for t in reversed(range(n)):
        if t == n - 1 or (t > 0 and (terminateds[t - 1] or truncateds[t - 1])):
            out[t] = values[t]  # bootstrap row
        elif terminateds[t]:
            out[t] = rewards[t]
        elif truncateds[t]:
            out[t] = rewards[t] + gamma * values[t + 1]
        else:
            out[t] = rewards[t] + gamma * ((1 - lambda_) * values[t + 1] + lambda_ * out[t + 1])
    return out.astype(np.float32)


def standardize(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(x - mean) / std over the rows where mask is true (ML-Agents: over the buffer)."""
    valid = x[mask.astype(bool)]
    if valid.size == 0:
        return np.zeros_like(x)
    return ((x - valid.mean()) / max(float(valid.std()), 1e-8)).astype(np.float32)


def gaussian_logp_per_dim(actions: torch.Tensor, mean: torch.Tensor,
                          log_std: torch.Tensor) -> torch.Tensor:
    """Log-density of each action dimension under N(mean, exp(log_std)^2)."""
    z = (actions - mean) * torch.exp(-log_std)
    return -0.5 * z * z - log_std - 0.5 * LOG_2PI


def gaussian_entropy(log_std: torch.Tensor) -> torch.Tensor:
    """Entropy of a diagonal Gaussian, averaged over action dimensions.

    ML-Agents' Gaussian entropy is the mean over dimensions, so beta means the same for a
    2-D (wheeled) and a 4-D (quad) action; a sum would weigh it 2x and 4x (RLlib's PPO,
    our baseline, keeps RLlib's sum)."""
    return (log_std + 0.5 * (LOG_2PI + 1.0)).mean(-1)


def explained_variance(targets: np.ndarray, predictions: np.ndarray) -> float:
    """1 - Var(targets - predictions) / Var(targets): 1 for a perfect critic, 0 for one
    that predicts the mean, negative for worse (NaN without variance in the targets)."""
    targets = np.asarray(targets, np.float64)
    var = targets.var()
    if targets.size < 2 or var == 0:
        return math.nan
    return float(1.0 - (targets - np.asarray(predictions, np.float64)).var() / var)


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    mask = mask.to(x.dtype)
    while mask.dim() < x.dim():
        mask = mask.unsqueeze(-1)
    mask = mask.expand_as(x)
    return (x * mask).sum() / mask.sum().clamp(min=1.0)


def clipped_policy_loss(logp: torch.Tensor, old_logp: torch.Tensor, advantages: torch.Tensor,
                        epsilon: float, mask: torch.Tensor,
                        weights: torch.Tensor | None = None) -> torch.Tensor:
    """-E[w min(r A, clip(r, 1-eps, 1+eps) A)] with the ratio r taken per action dimension
    and w a per-row weight (1 if not given)."""
    ratio = torch.exp(logp - old_logp)
    adv = advantages.unsqueeze(-1)
    surrogate = torch.min(ratio * adv, torch.clamp(ratio, 1.0 - epsilon, 1.0 + epsilon) * adv)
    if weights is not None:
        surrogate = surrogate * weights.unsqueeze(-1)
    return -masked_mean(surrogate, mask)


IMPORTANCE_CAP = 2.0
"""The largest importance weight a row gets (truncated importance sampling, as V-trace's
rho-bar: a rare action the sampler chose far less often than the clip policy would does
not dominate a minibatch)."""


def importance_weights(clip_logp: torch.Tensor, behaviour_logp: torch.Tensor,
                       mask: torch.Tensor) -> torch.Tensor:
    """pi_clip(a) / pi_behaviour(a) of each row's joint action, capped at IMPORTANCE_CAP,
    1 on masked rows (their stored values may be padding): the decoupled PPO objective's
    weight (Hilton et al. 2022, "Batch size-invariance for policy optimization"), which
    makes the clipped surrogate around pi_clip an expectation under pi_clip although
    pi_behaviour sampled the rows."""
    weights = torch.exp(clip_logp - behaviour_logp).clamp(max=IMPORTANCE_CAP)
    return torch.where(mask.bool(), weights, torch.ones_like(weights)).detach()


def trust_region_value_loss(values: torch.Tensor, old_values: torch.Tensor,
                            returns: torch.Tensor, epsilon: float,
                            mask: torch.Tensor) -> torch.Tensor:
    """E[max((G - v)^2, (G - v_old - clip(v - v_old, -eps, eps))^2)] (ML-Agents)."""
    clipped = old_values + torch.clamp(values - old_values, -epsilon, epsilon)
    return masked_mean(torch.max((returns - values) ** 2, (returns - clipped) ** 2), mask)


def poca_critic_loss(value_loss: torch.Tensor, baseline_loss: torch.Tensor) -> torch.Tensor:
    """ML-Agents' weighting of the critic heads: 0.5 * (value + 0.5 * baseline)."""
    return 0.5 * (value_loss + 0.5 * baseline_loss)

