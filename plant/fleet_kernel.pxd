# What other kernels may call of plant/fleet_kernel.pyx (agents/law_kernel.pyx cimports it:
# the look-ahead integrates eq. (4) with the same code as the model plant).

cdef struct Model:
    # the constant parts of eq. (4) for one robot (plant/mecanum.py, MecanumModel)
    double P[4][3]       # wheel matrix of eq. (2)
    double B0[3][4]      # B in the body frame: B(phi) = T(phi) B0
    double A0[3][3]      # viscous term, constant in the world frame
    double inv_R         # 1 / wheel radius
    double coulomb       # C_f m g R / 4, wheel torque of the smoothed Coulomb friction
    double inv_smooth    # 1 / omega_s in tanh(theta_dot / omega_s)
    double viscous       # C_theta R^2, wheel torque per wheel speed (pybullet plant's (P4))

cdef void model_from(Model* m, object model)
cdef void acceleration(const Model* m, double phi, const double* qd, const double* u,
                       double* acc) noexcept nogil
cdef void rk4(const Model* m, double* q, double* qd, const double* u, double h) noexcept nogil
cdef void saturate_velocity(double* v, double max_speed, double max_yaw) noexcept nogil
