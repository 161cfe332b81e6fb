"""`rsra web`: NASA Open MCT in the browser, fed by a gateway that is just another Zenoh client.

* :mod:`daq.web.dictionary` — the telemetry dictionary built from the rig config, the limits
  (noise budget, χ² band of the NIS, node states and flags) and the conversion of telemetry
  payloads into Open MCT points (pure: no I/O).
* :mod:`daq.web.history` — the bounded in-memory history and the telemetry files on disk
  (`rsra replay --out` JSONL, MCAP from `rsra export --mcap`) that answer history requests.
* :mod:`daq.web.server` — the HTTP/WebSocket server (aiohttp): the Open MCT files, the rsra
  plugin, the dictionary, history and real-time points, Host/Origin checks, bounded queues.
"""
