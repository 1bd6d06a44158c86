"""Hardware bridges: the same agents on real motor drivers (DESIGN §8).

- protocol.py + odrive_cansimple.dbc: ODrive CANSimple frames, encoded and
  decoded with cantools behind one interface (a CiA 402 driver can follow);
- bridge.py: one robot's bridge, a zenoh peer in place of the plant for that
  robot (``omnifleet bridge``); odometry.py, monitor.py, safety.py its pure parts;
- emulator.py: four drivers and the robot's dynamics on a CAN bus
  (``omnifleet emulate``), with frame loss, corruption and silent drivers;
- can_check.py: bring-up (``omnifleet can-check [--spin]``).

Not built yet: ``omnifleet run --plant can-emulated`` (the launcher starting a
bridge and an emulator per robot); see docs/hardware.md.
"""
