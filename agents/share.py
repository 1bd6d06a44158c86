"""What agent i tells the agents that listen to it (a_ij != 0; eqs. 14, 16): its leader
estimate, its robot's state and its formation reference, and how old its leader
information is (agents/degradation.py).

One type, in the law and on the wire: the law builds it, the agent sends it as it is in
its ``Reply`` (deploy/contract/wire.py), a neighbour's law reads it as it was decoded.
Its floats are bounded as every float on the wire is (``FLOAT_LIMIT``): msgspec checks
the bound as it decodes, in C, and NaN fails it too; a sender checks its own message the
same way before it puts it (deploy/runtime/transport.py), so a NaN never leaves.
"""

from __future__ import annotations

from typing import Annotated

import msgspec

FLOAT_LIMIT = 1e300  # no physical quantity here comes near it
Finite = Annotated[float, msgspec.Meta(ge=-FLOAT_LIMIT, le=FLOAT_LIMIT)]
FiniteVec3 = tuple[Finite, Finite, Finite]


class Share(msgspec.Struct, array_like=True, frozen=True, gc=False):
    """The seven fields, in the wire's order (an array: the field names never travel)."""

    q0_hat: FiniteVec3
    v0_hat: FiniteVec3
    q: FiniteVec3
    q_dot: FiniteVec3
    zeta: FiniteVec3
    zeta_dot: FiniteVec3
    info_age_s: Finite = 0.0  # how old the sender's leader information is (s)
