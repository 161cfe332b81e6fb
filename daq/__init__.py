"""The imperative shell: configuration, CANopen master, reader, runtime, telemetry, CLI."""
