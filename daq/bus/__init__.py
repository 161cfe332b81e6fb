"""The bus room: CAN/CANopen I/O — the EDS decode table, the frame tap and sample assembler,
the CANopen master and node verifier, the heartbeat supervisor, the recorder and the replay
reader, and the shared bus between processes. Imports nothing of the other rooms."""
