"""Characteristic diagrams (CDs) and what they need around them.

Training data from the FE model, input selection, regression, XML with a schema, the CD database and the CNC export:

* :mod:`hybridcomp.chardiag.cd` — :class:`CharDiagram` (evaluation, vectorised and single-point), :class:`CDSet`
* :mod:`hybridcomp.chardiag.fit` — input selection and the sparse regularised least-squares fit
* :mod:`hybridcomp.chardiag.training` — load cases → FE → training table
* :mod:`hybridcomp.chardiag.xmlio` — XML files validated against ``schema/cd.xsd``, hardened reading
* :mod:`hybridcomp.chardiag.db` — :class:`CDDatabase` (SQLite by default, any SQLAlchemy URL)
* :mod:`hybridcomp.chardiag.export` — compensation offsets for the CNC (generic table, Siemens 840D sl)
"""

from hybridcomp._lazy import lazy_exports
from hybridcomp._packages import refuse_top_level_import

refuse_top_level_import(__name__)  # hybridcomp.<package>, never the folder's own name

# module -> the public names it defines (imported on first use)
__all__, __getattr__, __dir__ = lazy_exports(__name__, {
    "cd": ("DIRECTIONS", "TARGETS", "CDError", "CDInput", "CDSet", "CharDiagram", "Term", "pose_key"),
    "fit": ("CDFitError", "FitOptions", "fit_cd", "fit_cd_set", "select_inputs"),
    "xmlio": ("CDXmlError", "cd_from_bytes", "cd_to_bytes", "read_cd", "write_cd"),
})
