"""Traces and G-code to thermal boundary conditions.

Data flow: trace CSV (streamed) or G-code → :class:`Increments` (load factors,
position histograms over the rail segments, spindle factor, air temperatures
per time increment) → :func:`boundary_conditions` (heat power per source and
rail segment, zone air) → ``models.loads.write_loads`` → ``hybridcomp simulate``.
:func:`signatures` gives the fixed-length load-case vectors the CD database
is searched by.
"""

from hybridcomp._lazy import lazy_exports
from hybridcomp._packages import refuse_top_level_import

refuse_top_level_import(__name__)  # hybridcomp.<package>, never the folder's own name

# module -> the public names it defines (imported on first use)
__all__, __getattr__, __dir__ = lazy_exports(__name__, {
    "bcs": ("boundary_conditions", "heat_powers", "source_factors", "standstill_powers", "write_bcs"),
    "gcode": ("GcodeError", "Motion", "increments_from_motion", "parse_gcode", "read_gcode", "sample_motion"),
    "increments": ("Increments", "increments_from_samples", "increments_from_trace"),
    "signature": ("SignatureLayout", "signature_distance", "signatures"),
    "trace": (
        "Samples", "TraceFileError", "TraceWarning", "read_trace_chunks", "samples", "write_trace",
        "zone_air_sources",
    ),
})
