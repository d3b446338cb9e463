"""Batch column names POCA adds (RLlib's own columns are ``Columns.*``)."""

GROUP_ROW = "poca_group_row"  # (rows,): the row's step in this update's group table
GROUP_TABLE = "poca_group_table"  # shared_data key: (obs, act, present) per step
TABLE_KEY = "poca_table_key"  # critic batch key: which of the critic's group tables
SELF_IDX = "poca_self_idx"  # (rows,): the slot of the row's own robot
GROUP_REW = "poca_group_rew"  # (rows,): the group reward of the step
RETURNS = "poca_returns"  # lambda-returns bootstrapped from V
OLD_VALUES = "poca_old_values"  # V at collection time (for value clipping)
OLD_BASELINES = "poca_old_baselines"  # b_i at collection time
VALUES = "poca_values"  # critic forward outputs
BASELINES = "poca_baselines"
