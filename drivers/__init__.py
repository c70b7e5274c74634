"""Hardware and link drivers (OAK camera, serial IMU, MAVLink). Only the service imports these; `vio` does not."""
