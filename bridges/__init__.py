"""Hardware bridges (python-can to motor drivers).

Not implemented yet: the CAN bridge and driver emulator are tracked by the
hardware-in-the-loop issue. Nothing in this package pretends otherwise.
"""
