"""`vio run`, the onboard daemon: buffers, worker threads, the status snapshot and the service around them.

    buffers  SensorBuffer, LatestState, RateWindow (bounded, thread-safe hand-overs)
    workers  the source and estimator threads
    outputs  the MAVLink/TUM output and recorder threads
    status   the status snapshot fields and the status file
    service  Service (supervision, readiness, watchdog) and the `vio run` command
"""
