"""Batch column names POCA adds (RLlib's own columns are ``Columns.*``)."""

GROUP_OBS = "poca_group_obs"  # (rows, slots, max obs dim): every robot's observation
GROUP_ACT = "poca_group_act"  # (rows, slots, max action dim): every robot's (clipped) action
GROUP_MASK = "poca_group_mask"  # (rows, slots): robot present at that step
SELF_IDX = "poca_self_idx"  # (rows,): the slot of the row's own robot
GROUP_REW = "poca_group_rew"  # (rows,): the group reward of the step
RETURNS = "poca_returns"  # lambda-returns bootstrapped from V
OLD_VALUES = "poca_old_values"  # V at collection time (for value clipping)
OLD_BASELINES = "poca_old_baselines"  # b_i at collection time
VALUES = "poca_values"  # critic forward outputs
BASELINES = "poca_baselines"
