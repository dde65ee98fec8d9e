"""The legs' names and how they meet at the platform (a leaf module).

Six legs, named as in every JointState of the rig; legs 2k-1 and 2k (1-based)
meet at platform vertex k (the paper's 6-3 arrangement, Fig. 1).
``params`` re-exports both names.
"""
from __future__ import annotations

import numpy as np

LEG_NAMES = tuple('leg_%d' % i for i in range(1, 7))
#: Legs 2k-1 and 2k (1-based) meet at platform vertex k.
LEG_VERTEX = np.array([0, 0, 1, 1, 2, 2])
