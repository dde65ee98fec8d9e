"""The legs' names and how they meet at the platform (a leaf module).

Six legs, named as in every JointState of the rig. On a 6-3 (the paper's,
Fig. 1), legs 2k-1 and 2k (1-based) meet at platform vertex k; on a 6-6, leg
i has its own platform joint i (``Mechanism.leg_vertex`` picks one).
``params`` re-exports both names.
"""
from __future__ import annotations

import numpy as np

LEG_NAMES = tuple('leg_%d' % i for i in range(1, 7))
#: Legs 2k-1 and 2k (1-based) meet at platform vertex k.
LEG_VERTEX = np.array([0, 0, 1, 1, 2, 2])
#: A 6-6: leg i meets platform joint i.
SIX_JOINTS = np.arange(6)
