"""Traces and G-code to thermal boundary conditions.

Data flow: trace CSV (streamed) or G-code → :class:`Increments` (load factors,
position histograms over the rail segments, spindle factor, air temperatures
per time increment) → :func:`boundary_conditions` (heat power per source and
rail segment, zone air) → ``fem.loads.write_loads`` → ``hybridcomp simulate``.
:func:`signatures` gives the fixed-length load-case vectors the CD database
is searched by.
"""

from hybridcomp.histogram.bcs import (
    boundary_conditions,
    heat_powers,
    source_factors,
    standstill_powers,
    write_bcs,
)
from hybridcomp.histogram.gcode import (
    GcodeError,
    Motion,
    increments_from_motion,
    parse_gcode,
    read_gcode,
    sample_motion,
)
from hybridcomp.histogram.increments import (
    Increments,
    increments_from_samples,
    increments_from_trace,
)
from hybridcomp.histogram.signature import (
    SignatureLayout,
    signature_distance,
    signatures,
)
from hybridcomp.histogram.trace import (
    Samples,
    TraceFileError,
    TraceWarning,
    read_trace_chunks,
    samples,
    write_trace,
    zone_air_sources,
)

__all__ = [
    "GcodeError",
    "Increments",
    "Motion",
    "Samples",
    "SignatureLayout",
    "TraceFileError",
    "TraceWarning",
    "boundary_conditions",
    "heat_powers",
    "increments_from_motion",
    "increments_from_samples",
    "increments_from_trace",
    "parse_gcode",
    "read_gcode",
    "read_trace_chunks",
    "sample_motion",
    "samples",
    "signature_distance",
    "signatures",
    "source_factors",
    "standstill_powers",
    "write_bcs",
    "write_trace",
    "zone_air_sources",
]
