"""Plants: the mecanum model (eqs. 1-4), model and kinematic plants, perception."""

from plant import fleet_kernel
from plant.kernels import checked

checked(fleet_kernel)  # a kernel built from another version of its source is refused
