"""Pure numerical core: the load-cell model, noise budget, filters and identification.

numpy in, numpy out; no I/O, no threads, no CAN, no Zenoh.
"""
