"""The imperative shell: configuration, CANopen master, reader, runtime, telemetry, CLI."""
import os

# One BLAS thread: the service's estimator thread, the identification worker and the bus
# threads share few cores, and a multi-threaded BLAS made filter designs 10-20x slower under
# load (measured: an EstimatorPipeline start 5-11 s instead of 0.5 s on 2 busy cores).
# Only a default: the user's environment wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
