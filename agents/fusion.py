"""Null-space priority fusion (26) and the behavior supervisor (erratum 8).

    v_d = v_1 + N_1 (v_2 + N_2 v_3),   N_k = I - J_k^+ J_k

The supervisor orders the behaviors by the configured priority (default
FOCB > FRCB > FDB). An inactive behavior contributes zero velocity and an
identity projector, which is the same as leaving it out of the chain.

When an avoidance behavior (FOCB, FRCB) takes part is the scenario's choice:
* ``inside``: whenever the body is inside its safety threshold (as printed, and
  as the authors' code does for FOCB);
* ``approaching`` (set-based, after Moe et al., "Set-based tasks within the
  singularity-robust multiple task-priority inverse kinematics framework"):
  inside the threshold AND the velocity fused without it would bring the body
  closer (J_1 v < 0). ``inside`` removes every radial motion, moving away
  included; two robots sent to one spot (the paper's narrow passage S =
  diag(1, 0) does exactly that to robots 2 and 3) then block each other in a
  column while the formation moves on. ``approaching`` lets the front robot go.

The arithmetic is the compiled law's (agents/law_kernel_sections/fusion.pxi);
tests/paper_oracle.py writes it again in numpy, the independent form the tests hold it to.
This module keeps the default priority.
"""

from __future__ import annotations

DEFAULT_PRIORITY = ("FOCB", "FRCB", "FDB")
