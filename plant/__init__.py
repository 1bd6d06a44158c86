"""Plants: the mecanum model (eqs. 1-4), model and kinematic plants, perception."""
