"""The analysis room: off-line work over recordings and published records — calibration,
sweeps, reports, exports, the tare. Imports the bus and runtime rooms, never the command line."""
