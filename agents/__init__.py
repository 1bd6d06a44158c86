"""The robot agent: estimator (14), ESO (39), behaviors (15)-(25), fusion (26),
fully actuated controller (34)-(36), (40)-(42). Pure math; node I/O lives apart."""

from agents import law_kernel
from plant.kernels import checked

checked(law_kernel)  # a kernel built from another version of its source is refused
