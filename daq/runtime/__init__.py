"""The runtime room: the service — its sources of samples, the estimator loop (pipeline),
the supervised identification worker, the outputs (Zenoh telemetry) and persistence of the
posterior. Imports the bus room, never the analysis or the command line."""
