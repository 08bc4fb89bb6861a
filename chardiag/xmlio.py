"""CD files: XML written and read with lxml, validated against the shipped XSD (``schema/cd.xsd``).

Numbers are written in Python's shortest round-trip form (``repr``), so a
read gives back the same bits and a re-write the same bytes.

Reading is hardened for files that come from elsewhere: only a regular file
is opened (a named pipe, a device or a directory is refused without blocking);
the size is checked before anything is read (``max_bytes``, default 16 MiB); a
document type declaration or entity declaration is refused before parsing (no
DTD, no external entity, no entity expansion: no billion laughs); the parser
never touches the network; the document must validate against the schema; and
the CD it describes must be plausible (:class:`~hybridcomp.chardiag.cd.CharDiagram`
checks finite, bounded values and names without control characters).
"""

from __future__ import annotations

import math
import os
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np
from lxml import etree

from hybridcomp.chardiag.cd import CDError, CDInput, CharDiagram, Term
from hybridcomp.errors import HybridcompError
from hybridcomp.models.toml import open_regular_file
from hybridcomp.safeio import write_bytes_atomic

NS = "urn:hybridcomp:characteristic-diagram:1"
FORMAT_VERSION = 1
MAX_BYTES = 16 * 1024 * 1024
_Q = f"{{{NS}}}"


class CDXmlError(HybridcompError, ValueError):
    """A CD file is unsafe, invalid or for another machine; the message names the file, line and field."""


@lru_cache(maxsize=1)
def schema() -> etree.XMLSchema:
    """The shipped XSD."""
    text = resources.files("hybridcomp.chardiag").joinpath("schema/cd.xsd").read_bytes()
    return etree.XMLSchema(etree.fromstring(text, _parser()))


def _parser() -> etree.XMLParser:
    return etree.XMLParser(resolve_entities=False, no_network=True, load_dtd=False, dtd_validation=False,
                           huge_tree=False, remove_blank_text=True, remove_comments=True, remove_pis=True)


def _f(v: float) -> str:
    """An xs:double: the shortest round-trip form, and ``NaN``, ``INF``, ``-INF`` as the schema spells them."""
    v = float(v)
    if math.isfinite(v):
        return repr(v)
    return "NaN" if math.isnan(v) else "INF" if v > 0 else "-INF"


def cd_to_element(cd: CharDiagram) -> etree._Element:
    """The CD as an XML element tree (not yet validated: see :func:`cd_to_bytes`)."""
    E = lambda tag, **attrs: etree.Element(_Q + tag, {k: str(v) for k, v in attrs.items()})  # noqa: E731
    root = etree.Element(_Q + "characteristicDiagram", {"formatVersion": str(FORMAT_VERSION)}, nsmap={None: NS})
    root.append(E("machine", name=cd.machine, sha256=cd.machine_sha256))
    pose = etree.SubElement(root, _Q + "pose")
    for a, p in cd.pose_mm:
        pose.append(E("axis", name=a, position_mm=_f(p)))
    etree.SubElement(root, _Q + "direction").text = cd.direction
    inputs = etree.SubElement(root, _Q + "inputs")
    for i in cd.inputs:
        inputs.append(E("input", name=i.name, unit=i.unit, active="true" if i.active else "false", min=_f(i.min),
                        max=_f(i.max), supportPoints=i.n_support, reason=i.reason))
    terms = etree.SubElement(root, _Q + "terms")
    for t in cd.terms:
        el = E("term", inputs=" ".join(cd.inputs[j].name for j in t.inputs))
        etree.SubElement(el, _Q + "values").text = " ".join(_f(v) for v in t.values.ravel())
        terms.append(el)
    root.append(E("regularisation", smoothing=_f(cd.smoothing), ridge=_f(cd.ridge)))
    lc = E("loadCase", name=cd.load_case)
    etree.SubElement(lc, _Q + "signature").text = " ".join(_f(v) for v in cd.signature)
    root.append(lc)
    tref = etree.SubElement(root, _Q + "referenceTemperatures")
    for s, T in cd.t_reference_degC:
        tref.append(E("sensor", name=s, T_degC=_f(T)))
    fit = etree.SubElement(root, _Q + "fit")
    for k, v in cd.fit:
        fit.append(E("statistic", name=k, value=_f(v)))
    etree.SubElement(root, _Q + "created").text = cd.created
    root.append(E("software", name="hybridcomp", version=cd.software_version))
    return root


def cd_to_bytes(cd: CharDiagram) -> bytes:
    """The CD as a schema-valid XML document (UTF-8)."""
    root = cd_to_element(cd)
    schema().assertValid(root)
    return etree.tostring(root, xml_declaration=True, encoding="UTF-8", pretty_print=True)


def write_cd(path: str | Path, cd: CharDiagram) -> Path:
    """Write a CD file (atomically: a temporary file renamed into place, removed if the write fails)."""
    return write_bytes_atomic(path, cd_to_bytes(cd))


def _check_raw(data: bytes, source: str, max_bytes: int) -> None:
    if len(data) > max_bytes:
        raise CDXmlError(f"{source}: {len(data)} bytes is over the limit of {max_bytes} bytes for a CD file")
    if b"<!DOCTYPE" in data or b"<!ENTITY" in data:
        raise CDXmlError(f"{source}: document type or entity declarations are not allowed in a CD file")


def cd_from_bytes(data: bytes, source: str = "<bytes>", machine=None, max_bytes: int = MAX_BYTES,
                  allow_modified_machine: bool = False) -> CharDiagram:
    """Parse, validate and load a CD document.

    Parameters
    ----------
    data : the document
    source : name for error messages (the file name)
    machine : a ``models.Machine``: the CD must be for it (name, file hash unless ``allow_modified_machine``)
        and use only its sensors and axes
    max_bytes : size limit [bytes]
    """
    _check_raw(data, source, max_bytes)
    try:
        root = etree.fromstring(data, _parser())
    except etree.XMLSyntaxError as exc:
        raise CDXmlError(f"{source}: not well-formed XML: {exc}") from None
    if root.getroottree().docinfo.doctype:
        raise CDXmlError(f"{source}: document type declarations are not allowed in a CD file")
    sch = schema()
    if not sch.validate(root):
        err = sch.error_log.last_error
        raise CDXmlError(f"{source}: line {err.line}: not a valid CD file: {err.message}")
    try:
        cd = _from_element(root)
    except (CDError, ValueError) as exc:
        raise CDXmlError(f"{source}: {exc}") from None
    if machine is not None:
        check_machine(cd, machine, source, allow_modified_machine)
    return cd


def read_cd(path: str | Path, machine=None, max_bytes: int = MAX_BYTES, allow_modified_machine: bool = False) -> CharDiagram:
    """Read a CD file (see :func:`cd_from_bytes`); the size is checked before the file is read."""
    path = Path(path)
    with open_regular_file(path, CDXmlError, "CD file") as fh:
        size = os.fstat(fh.fileno()).st_size
        if size > max_bytes:
            raise CDXmlError(f"{path}: {size} bytes is over the limit of {max_bytes} bytes for a CD file")
        try:
            data = fh.read(max_bytes + 1)
        except OSError as exc:
            raise CDXmlError(f"{path}: cannot read CD file: {exc.strerror or exc}") from None
    return cd_from_bytes(data, str(path), machine, max_bytes, allow_modified_machine)


def check_machine(cd: CharDiagram, machine, source: str = "CD", allow_modified_machine: bool = False) -> None:
    """Raise :class:`CDXmlError` unless the CD is for ``machine`` and names only its sensors and axes.

    Checked: the inputs, the reference temperatures and the pose.
    """
    if cd.machine != machine.name:
        raise CDXmlError(f"{source}: machine: the CD is for {cd.machine!r}, not for {machine.name!r}")
    if not allow_modified_machine and cd.machine_sha256 and cd.machine_sha256 != machine.sha256:
        raise CDXmlError(f"{source}: machine sha256: the CD was trained on another version of the machine file "
                         f"{machine.name!r} ({cd.machine_sha256[:12]}… vs {machine.sha256[:12]}…)")
    sensors = {s.name for s in machine.sensors}
    axes = {a.name for a in machine.axes}
    for i in cd.inputs:
        known = sensors if i.unit == "degC" else axes
        if i.name not in known:
            kind = "sensor" if i.unit == "degC" else "axis"
            raise CDXmlError(f"{source}: input {i.name!r}: machine {machine.name!r} has no {kind} of that name "
                             f"(has: {', '.join(sorted(known))})")
    for name, _ in cd.t_reference_degC:  # the monitor compares these with the machine's sensors
        if name not in sensors:
            raise CDXmlError(f"{source}: referenceTemperatures sensor {name!r}: machine {machine.name!r} has no sensor "
                             f"of that name (has: {', '.join(sorted(sensors))})")
    unknown_pose = [a for a, _ in cd.pose_mm if a not in axes]
    if unknown_pose:
        raise CDXmlError(f"{source}: pose: machine {machine.name!r} has no axis {unknown_pose[0]!r}")


def _doubles(text: str | None) -> np.ndarray:
    return np.array([float(v) for v in (text or "").split()], float)


def _from_element(root) -> CharDiagram:
    ch = {el.tag[len(_Q):]: el for el in root}
    m = ch["machine"]
    inputs = tuple(
        CDInput(name=el.get("name"), unit=el.get("unit"), active=el.get("active") in ("true", "1"),
                min=float(el.get("min")), max=float(el.get("max")), n_support=int(el.get("supportPoints")),
                reason=el.get("reason", ""))
        for el in ch["inputs"])
    index = {i.name: k for k, i in enumerate(inputs)}
    terms = []
    for k, el in enumerate(ch["terms"]):
        names = el.get("inputs").split()
        twice = [n for n in names if names.count(n) > 1]
        if twice:
            raise ValueError(f"term {k}: input {twice[0]!r} appears twice in its inputs {' '.join(names)!r}")
        missing = [n for n in names if n not in index]
        if missing:
            raise ValueError(f"term {k}: input {missing[0]!r} is not declared in <inputs>")
        idx = tuple(index[n] for n in names)
        shape = tuple(inputs[j].n_support for j in idx)
        vals = _doubles(el.find(_Q + "values").text)
        if vals.size != math.prod(shape):  # exact integers: a huge supportPoints cannot wrap around
            raise ValueError(f"term {k} ({' '.join(names)}): {vals.size} values, the grid {shape} needs {math.prod(shape)}")
        terms.append(Term(inputs=idx, values=vals.reshape(shape)))
    reg = ch["regularisation"]
    lc = ch["loadCase"]
    return CharDiagram(
        machine=m.get("name"),
        machine_sha256=m.get("sha256"),
        pose_mm=tuple((el.get("name"), float(el.get("position_mm"))) for el in ch["pose"]),
        direction=ch["direction"].text.strip(),
        inputs=inputs,
        terms=tuple(terms),
        smoothing=float(reg.get("smoothing")),
        ridge=float(reg.get("ridge")),
        load_case=lc.get("name"),
        signature=_doubles(lc.find(_Q + "signature").text),
        t_reference_degC=tuple((el.get("name"), float(el.get("T_degC"))) for el in ch["referenceTemperatures"]),
        fit=tuple((el.get("name"), float(el.get("value"))) for el in ch["fit"]),
        created=ch["created"].text or "",
        software_version=ch["software"].get("version"),
    )
