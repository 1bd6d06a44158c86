"""Hardware bridges: the same agents on real motor drives (docs/hardware.md). Imports plant,
python-can and the drive protocols' libraries (cantools, canopen) only.

- driver.py: what a bridge needs from any drive, in neutral terms (``WheelDriver``,
  ``WheelReport``, ``DriveState``); drivers.py names the plug-ins (``--driver``):
- odrive.py + odrive_cansimple.dbc: ODrive CANSimple, frames encoded and decoded with
  the DBC's layouts, and its host plug-in;
- cia402.py (the CiA 402 state machine), cia402_driver.py (its host plug-in on the
  canopen library: EDS, NMT, SDO, PDOs, SYNC), cia402_pdo.py (PDO payload packing),
  cia402_drive.eds (the emulated drive's object dictionary);
- monitor.py, odometry.py, safety.py: the bridge's pure parts, in neutral terms (the
  bridge process itself lives in deploy/nodes/);
- drive_emulator.py (a robot's dynamics and bus faults), odrive_emulator.py and
  cia402_emulator.py (four drives of each protocol on it), fleet_emulator.py (several
  robots in one process): ``omnifleet emulate`` and ``omnifleet run --plant can-emulated``.
"""
