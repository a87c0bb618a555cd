"""Array aliases with their shapes, shared by the whole core.

Dimensions: B episodes in a batch, N agents, p tasks, q idle locations, S sites, L severity levels.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

Levels = IntArray  # (B, p) true severity level of every task
Actions = IntArray  # (B, N) index into G-bar: tasks 0..p-1, idle locations p..p+q-1
Observations = IntArray  # (B, N) observed level of the agent's task, -1 when idle
Messages = IntArray  # (B, N) level broadcast by each agent after its channel, -1 when idle
# (B, N, S, L, ..., L) each agent's joint belief per site, one level axis per slot (K: the scenario's kinds, or the
# most tasks at one site when that is fewer; htlm_agent.mind.belief)
Belief = FloatArray
Marginals = FloatArray  # (B, N, p, L) per-task marginals of the belief
Knowledge = FloatArray  # (B, N, p*L + |G|) Q-network input: marginals + one-hot previous assignment
