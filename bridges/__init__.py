"""Hardware bridges: the same agents on real motor drivers (docs/hardware.md). Imports
plant/ and python-can only; the processes that run these (``omnifleet bridge``,
``omnifleet emulate``, ``omnifleet can-check``) live in deploy/nodes/.

- protocol.py + odrive_cansimple.dbc: the :class:`~bridges.protocol.DriverProtocol`
  interface and ODrive CANSimple frames, encoded and decoded with cantools (a CiA 402
  driver can follow behind the same interface); drivers.py names the protocols a bridge
  speaks (``omnifleet bridge --driver``);
- odometry.py (wheel speeds -> body twist, eq. 1 -> pose), monitor.py (heartbeats and
  driver errors -> robot health), safety.py (which torque may go on the bus: stale
  command or e-stop -> zero): the bridge's pure parts;
- drive_emulator.py: four drives and one robot's dynamics on a CAN bus, with frame loss,
  corruption and silent drivers; fleet_emulator.py: several robots' in one process.

``omnifleet run --plant can-emulated`` starts an agent and a bridge per robot and one
driver emulator for the fleet (docs/hardware.md).
"""
