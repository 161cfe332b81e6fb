"""The telemetry payloads' schema: every key's fields with their JSON types and units, kept
equal to the tables of docs/telemetry.md (tests/test_export.py checks it), the JSON Schema of
each key built from it, and a record's log time (its acquisition time). Shared by the outputs
(Foxglove) and the exports (MCAP, Parquet)."""
from __future__ import annotations

import math

# -- telemetry payloads: fields, JSON types and units (docs/telemetry.md §2) -----------------
# (path, JSON type, unit) per key, in the order of the docs' tables; "<node>"/"<cell>" stand
# for any name, "x[]" for the elements of the list x. Types: integer, number, string, boolean,
# object, or array:<element type>. Every value may also be null (strict JSON, telemetry.md).
VEC6 = "N, N·m"
FIELDS: dict[str, list[tuple[str, str, str]]] = {
    "hub_loads": [
        ("seq", "integer", ""), ("sync", "integer", ""), ("t", "number", "s (UNIX)"),
        ("frame", "string", ""), ("H", "array:number", VEC6), ("H_static", "array:number", VEC6),
        ("sigma_angles", "array:number", VEC6), ("sigma_filter", "array:number", VEC6),
        ("omega", "number", "rad/s"), ("flags", "array:string", "")],
    "channels": [
        ("seq", "integer", ""), ("t", "number", "s (UNIX)"), ("T", "array:number", "N"),
        ("accel", "array:array:number", "m/s²"), ("I", "array:number", VEC6),
        ("omega", "number", "rad/s"), ("azimuth", "number", "rad"),
        ("known_H", "array:number", VEC6), ("drive", "array:number", "channel units"),
        ("status", "object", ""), ("status.<cell>", "integer", "")],
    "innovations": [
        ("seq", "integer", ""), ("t", "number", "s (UNIX)"), ("e", "array:number", VEC6),
        ("nis", "number", "")],
    "angles": [
        ("t", "number", "s (UNIX)"), ("seq", "integer", ""), ("mode", "string", ""),
        ("content", "string", ""), ("accepted", "boolean", ""), ("reason", "string", ""),
        ("detail", "string", ""),
        ("names", "array:string", ""), ("alpha", "array:number", "rad"),
        ("P", "array:array:number", "rad²"), ("sigma_cr", "array:number", "rad"),
        ("sigma_cr_corrected", "array:number", "rad"), ("determined", "integer", ""),
        ("window_determined", "integer", ""),
        ("information", "number", ""), ("nu", "number", ""), ("cost", "number", ""),
        ("iterations", "integer", ""), ("window", "array:integer", ""),
        ("applies_from_seq", "integer", ""), ("late", "boolean", ""),
        ("restarted", "boolean", ""), ("condition", "number", ""),
        ("structure", "string", ""), ("candidates", "array:object", ""),
        ("next_conditions", "array:object", ""), ("next_conditions[].H", "array:number", VEC6),
        ("next_conditions[].information_gain", "number", "nats"),
        ("next_conditions[].by_structure", "object", ""),
        ("next_conditions[].by_structure.constant", "number", "nats"),
        ("next_conditions[].by_structure.cell_gain", "number", "nats"),
        ("structure_fit", "object", ""), ("structure_fit.structure", "string", ""),
        ("structure_fit.parameters", "array:string", ""),
        ("structure_fit.alpha0", "array:number", "rad"),
        ("structure_fit.beta", "array:number", "SI"),
        ("structure_fit.alpha0_sigma", "array:number", "rad"),
        ("structure_fit.beta_sigma", "array:number", "SI"),
        ("structure_fit.T_ref", "array:number", "N"),
        ("explanation", "string", ""), ("hint", "string", ""),
        ("drift", "object", ""), ("drift.rate", "array:number", "rad/s"),
        ("drift.rate_sigma", "array:number", "rad/s"), ("drift.statistic", "number", ""),
        ("drift.dof", "integer", ""), ("drift.limit", "number", ""),
        ("drift.rejects_constant", "boolean", ""), ("drift.explains", "boolean", ""),
        ("drift.misfit", "number", ""), ("drift.misfit_dof", "integer", ""),
        ("drift.windows", "integer", ""), ("drift.span_s", "number", "s"),
        ("drift.restarted", "boolean", ""), ("drift.selected", "boolean", ""),
        ("samples_used", "integer", ""), ("nonlinearity", "number", ""),
        ("missing_inputs", "array:object", ""),
        ("missing_inputs[].input", "string", ""), ("missing_inputs[].fraction", "number", ""),
        ("load_excursion", "object", ""), ("load_excursion.delta", "array:number", "N, N·m"),
        ("load_excursion.sigma", "number", "rad"),  # one σ, the same for every angle
        ("reference_move", "object", ""), ("reference_move.delta", "array:number", "N, N·m"),
        ("reference_move.sigma", "number", "rad"),
        ("advice", "object", ""), ("advice.determined", "integer", ""),
        ("advice.next", "number", ""), ("advice.n_scored", "integer", ""),
        ("advice.accelerometers", "array:object", ""),
        ("advice.accelerometers[].name", "string", ""),
        ("advice.accelerometers[].position_m", "array:number", "m"),
        ("advice.accelerometers[].determined", "integer", ""),
        ("advice.accelerometers[].gain", "integer", ""),
        ("advice.accelerometers[].next", "number", ""),
        ("advice.manoeuvres", "array:object", ""), ("advice.manoeuvres[].axis", "string", ""),
        ("advice.manoeuvres[].rms", "number", "N, N·m"),
        ("advice.manoeuvres[].determined", "integer", ""),
        ("advice.manoeuvres[].gain", "integer", ""), ("advice.manoeuvres[].next", "number", ""),
        ("advice.window", "object", ""), ("advice.window.extra_s", "number", "s"),
        ("advice.window.gain", "integer", ""),
        ("advice.best", "object", ""), ("advice.best.kind", "string", ""),
        ("advice.best.name", "string", ""), ("advice.best.gain", "integer", ""),
        ("advice.best.next", "number", "")],
    "health": [
        ("t", "number", "s (UNIX)"), ("nodes", "object", ""),
        ("nodes.<node>.state", "string", ""), ("nodes.<node>.heartbeat_age", "number", "s"),
        ("nodes.<node>.required", "boolean", ""), ("nodes.<node>.boots", "integer", ""),
        ("nodes.<node>.losses", "integer", ""), ("nodes.<node>.emcy_count", "integer", ""),
        ("nodes.<node>.emcy", "array:object", ""),
        ("nodes.<node>.emcy[].t", "number", "s (UNIX)"),
        ("nodes.<node>.emcy[].code", "integer", ""),
        ("nodes.<node>.emcy[].register", "integer", ""),
        ("nodes.<node>.emcy[].info", "string", ""),
        ("nodes.<node>.emcy[].length", "integer", "bytes"),
        ("nodes.<node>.identity", "object", ""),
        ("nodes.<node>.identity.vendor-ID", "integer", ""),
        ("nodes.<node>.identity.product code", "integer", ""),
        ("nodes.<node>.identity.revision number", "integer", ""),
        ("nodes.<node>.identity.serial number", "integer", ""),
        ("nodes.<node>.error", "string", ""),
        *[(f"bus.{n}", "integer", "") for n in (
            "frames", "errors", "bus_off", "unknown", "malformed", "duplicate", "orphan",
            "remote", "callback_errors")],
        ("bus.late", "integer", ""),
        *[(f"samples.{n}", "integer", "") for n in ("complete", "incomplete", "lost")],
        ("sync", "object", ""), ("sync.duplicate", "integer", ""),
        ("sync.bad_timestamp", "integer", ""), ("sync.late_received", "integer", ""),
        ("sync.discontinuities", "integer", ""),
        ("sync.gaps", "integer", ""), ("sync.gap_longest_s", "number", "s"),
        ("sync.late", "integer", ""),
        ("sync.periods_not_taken", "integer", ""), ("sync.rate_hz", "number", "samples/s"),
        ("sync.rate_low", "boolean", ""),
        ("queues", "object", ""),
        *[(f"queues.samples.{n}", "integer", "") for n in (
            "depth", "size", "max_depth", "dropped", "blocked")],
        ("queues.master_events.depth", "integer", ""),
        ("queues.master_events.dropped", "integer", ""),
        *[(f"queues.identification.{n}", "integer", "") for n in (
            "submitted", "dropped", "errors")],
        ("identification", "object", ""), ("identification.worker", "string", ""),
        ("identification.pid", "integer", ""), ("identification.deaths", "integer", ""),
        ("identification.restarts", "integer", ""), ("identification.last_death", "string", ""),
        ("identification.off_reason", "string", ""),
        ("identification.save_error", "string", ""),
        ("identification.save_failures", "integer", ""),
        ("queues.publisher.depth", "integer", ""), ("queues.publisher.dropped", "integer", ""),
        ("estimator.implausible_omega", "integer", ""),
        ("estimator.design_errors", "integer", ""),
        ("estimator.hub_kernel", "string", ""), ("estimator.hub_kernel_samples", "integer", ""),
        ("estimator.inertial", "string", ""), ("estimator.harmonic_phase", "string", ""),
        ("estimator.azimuth_missing", "integer", ""),
        ("estimator.azimuth_refused", "integer", ""), ("estimator.stuck_samples", "integer", ""),
        ("estimator.stuck_episodes", "integer", ""),
        ("estimator.stuck_now", "array:string", ""),
        ("estimator.stuck_untested", "array:string", ""),
        ("recording.active", "boolean", ""), ("recording.dir", "string", ""),
        ("recording.format", "string", ""), ("recording.frames", "integer", ""),
        ("recording.bytes", "integer", "bytes"), ("recording.files", "integer", ""),
        ("recording.dropped", "integer", ""),
        *[(f"recording.queue.{n}", "integer", "") for n in (
            "depth", "size", "queued", "max_depth", "overflow")],
        ("recording.error", "string", ""),
        ("latency_ms.p50", "number", "ms"), ("latency_ms.p99", "number", "ms"),
        ("latency_ms.max", "number", "ms"), ("latency_ms.deadline_misses", "integer", ""),
        ("foxglove.clients", "integer", ""), ("foxglove.connections", "integer", ""),
        ("foxglove.refused", "integer", ""), ("foxglove.published", "integer", ""),
        ("foxglove.errors", "integer", ""),
        ("warnings", "array:string", "")],
}


def _type_schema(jtype: str) -> dict:
    if jtype.startswith("array:"):
        return {"type": ["array", "null"], "items": _type_schema(jtype[6:])}
    return {"type": [jtype, "null"]}


def json_schema(key: str) -> dict:
    """The JSON Schema (draft 2020-12) of one telemetry key's payload, from :data:`FIELDS`:
    nested objects by path, names (``<node>``) as additionalProperties, units in the
    descriptions."""
    root: dict = {"$schema": "https://json-schema.org/draft/2020-12/schema",
                  "title": f"rsra {key}", "type": "object", "properties": {}}

    def node_for(parts: list[str]) -> dict:
        cur = root
        for p in parts:
            if p.endswith("[]"):
                cur = cur["properties"].setdefault(p[:-2], _type_schema("array:object"))
                cur = cur["items"]
                cur.setdefault("properties", {})
                continue
            if p.startswith("<"):
                cur = cur.setdefault("additionalProperties", {"type": "object",
                                                              "properties": {}})
            else:
                cur = cur["properties"].setdefault(p, {"type": ["object", "null"],
                                                       "properties": {}})
            cur.setdefault("properties", {})
        return cur

    for path, jtype, unit in FIELDS[key]:
        *parents, last = path.split(".")
        parent = node_for(parents)
        sch = _type_schema(jtype)
        if unit:
            sch["description"] = f"unit: {unit}"
        if last.startswith("<"):
            prev = parent.get("additionalProperties", {})
            parent["additionalProperties"] = {**prev, **sch} if "properties" not in prev \
                else prev
            continue
        if jtype == "object" or jtype == "array:object":
            old = parent["properties"].get(last)
            if old is not None:  # declared earlier as a parent
                continue
        parent["properties"][last] = sch
    return root


def log_time_ns(payload: dict, last: int) -> int:
    """The MCAP log time of a record: its acquisition time ``t`` in ns (the last one when
    the record has none)."""
    t = payload.get("t")
    if isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t):
        return round(t * 1e9)
    return last
