"""The LFP container of Lytro files: ``.lfp`` pictures and ``data.C.N`` backup bundles.

Layout (lytro-f01.md sections 1.1-1.2): a 16-byte file header, then sections, each a
96-byte header (8-byte magic, big-endian int64 length, 80-byte NUL-padded ``sha1-`` ref),
the data, and NUL padding to the next 16-byte boundary. The ``LFM`` section holds the
JSON table of contents, whose ``...Ref`` fields name ``LFC`` sections by their ref.

Sections are found by their magic and indexed by ref, never by position; every SHA-1 is
checked. `inspect_container` reads a damaged file without raising and reports what is wrong.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

from analysis.errors import ChecksumError, FormatError, MetadataError, MissingSectionError, TruncatedFileError

FILE_MAGIC = b"\x89LFP\r\n\x1a\n"
FILE_HEADER = FILE_MAGIC + b"\x00\x00\x00\x01" + b"\x00\x00\x00\x00"
LFM_MAGIC = b"\x89LFM\r\n\x1a\n"
LFC_MAGIC = b"\x89LFC\r\n\x1a\n"
_KIND_OF_MAGIC = {LFM_MAGIC: "LFM", LFC_MAGIC: "LFC"}
_MAGIC_OF_KIND = {v: k for k, v in _KIND_OF_MAGIC.items()}

SECTION_HEADER_BYTES = 96
REF_FIELD_BYTES = 80
ALIGNMENT = 16

_REF_RE = re.compile(r"sha1-[0-9a-f]{40}")


def sha1_ref(data: bytes | bytearray | memoryview) -> str:
    """The section ref of ``data``: ``"sha1-"`` and its SHA-1 in 40 lowercase hex digits.

    Examples
    --------
    >>> sha1_ref(b"")
    'sha1-da39a3ee5e6b4b0d3255bfef95601890afd80709'
    """
    return "sha1-" + hashlib.sha1(data).hexdigest()


def json_bytes(obj: Any) -> bytes:
    """JSON in the camera's layout (tab indents, ``"key" : value``), UTF-8 encoded.

    NumPy scalars and arrays (as a simulator may put in metadata) are written as plain numbers
    and lists; NaN and infinities are refused, since the camera's readers cannot parse them.

    Raises
    ------
    MetadataError
        If ``obj`` holds something JSON cannot represent.
    """
    try:
        text = json.dumps(obj, indent="\t", separators=(",", " : "), ensure_ascii=False,
                          allow_nan=False, default=_plain)
    except (TypeError, ValueError) as exc:
        raise MetadataError(f"metadata cannot be written as JSON: {exc}; use plain numbers, "
                            "strings, lists and dicts") from None
    return text.encode("utf-8")


def _plain(obj: Any) -> Any:
    for method in ("tolist", "item"):  # numpy arrays and scalars, without importing numpy here
        if callable(getattr(obj, method, None)):
            return getattr(obj, method)()
    raise TypeError(f"{type(obj).__name__} is not JSON serializable")


def parse_json(data: bytes | bytearray | memoryview, *, what: str) -> Any:
    """Parse JSON metadata as the camera writes it.

    A UTF-8 byte-order mark and any bytes after the complete top-level value (the camera
    pads some files) are tolerated.

    Raises
    ------
    MetadataError
        If the bytes are not UTF-8 or do not start with a JSON value; ``what`` names the source.
    """
    try:
        text = bytes(data).decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise MetadataError(f"{what} is not UTF-8 text ({exc}); is it really JSON metadata?") from None
    start = len(text) - len(text.lstrip())
    try:
        value, _ = json.JSONDecoder().raw_decode(text, start)
    except json.JSONDecodeError as exc:
        raise MetadataError(f"{what} is not valid JSON ({exc}); the file is damaged or not Lytro metadata") from None
    return value


@dataclass(frozen=True)
class Section:
    """One section of a container: ``kind`` is ``"LFM"`` or ``"LFC"``, ``sha1`` its ref.

    ``offset`` is where its 96-byte header starts in the file; ``data`` may be a memoryview
    into the file's bytes (no copy of a 16 MB image).
    """

    kind: str
    sha1: str
    offset: int
    data: bytes | memoryview

    @property
    def length(self) -> int:
        return len(self.data)


@dataclass
class LfpContainer:
    """A parsed container: its sections in file order and the LFM table of contents."""

    sections: list[Section]
    toc: dict

    def __post_init__(self) -> None:
        self._by_ref = {s.sha1: s for s in self.sections}

    def section(self, ref: str) -> Section:
        """The section named ``ref``.

        Raises
        ------
        MissingSectionError
            If no section has that ref; the message says which TOC field refers to it.
        """
        found = self._by_ref.get(ref)
        if found is None:
            users = [path for path, r in iter_refs(self.toc) if r == ref]
            by = f" (referred to by {', '.join(users)})" if users else ""
            raise MissingSectionError(
                f"section {ref}{by} is not in the file; the file was stripped or cut short, "
                "get the complete file from the camera again")
        return found

    def json_section(self, ref: str) -> dict:
        """The section named ``ref`` parsed as a JSON object (MetadataError if it is not one)."""
        value = parse_json(self.section(ref).data, what=f"section {ref}")
        if not isinstance(value, dict):
            raise MetadataError(f"section {ref} holds JSON {type(value).__name__}, not an object")
        return value

    def missing_refs(self) -> list[tuple[str, str]]:
        """``(toc_path, ref)`` of every TOC ``...Ref`` field whose section is not in the file."""
        return [(path, ref) for path, ref in iter_refs(self.toc) if ref not in self._by_ref]


def iter_refs(toc: Any, path: str = "") -> Iterator[tuple[str, str]]:
    """Every ``(json_path, ref)`` in a TOC whose key ends in ``Ref`` and holds a ``sha1-`` string.

    ``derivationArray`` entries name pictures this one came from, not sections, so they are
    not refs in this sense.
    """
    if isinstance(toc, dict):
        for key, value in toc.items():
            sub = f"{path}.{key}" if path else key
            if isinstance(value, str) and key.endswith("Ref") and value.startswith("sha1-"):
                yield sub, value
            else:
                yield from iter_refs(value, sub)
    elif isinstance(toc, list):
        for i, value in enumerate(toc):
            yield from iter_refs(value, f"{path}[{i}]")


@dataclass(frozen=True)
class SectionReport:
    """What `inspect_container` found about one section."""

    kind: str
    sha1: str
    offset: int
    length: int
    sha1_ok: bool


@dataclass
class ContainerReport:
    """The outcome of `inspect_container`: everything readable, and every problem found."""

    sections: list[SectionReport] = field(default_factory=list)
    toc: dict | None = None
    missing_refs: list[tuple[str, str]] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    container: LfpContainer | None = None  # the readable sections and the TOC, when there is one

    @property
    def ok(self) -> bool:
        return not self.problems


def _check_file_header(buf: memoryview) -> None:
    if len(buf) < len(FILE_HEADER):
        if bytes(buf) == FILE_MAGIC[:len(buf)] or bytes(buf[:8]) == FILE_MAGIC:
            raise TruncatedFileError(f"the file ends after {len(buf)} bytes, inside the 16-byte LFP header")
        raise FormatError("not an LFP file (too short for the 16-byte header); "
                          "expected a Lytro .lfp or data.C.N file")
    if bytes(buf[:8]) != FILE_MAGIC:
        raise FormatError(f"not an LFP file: starts with {bytes(buf[:8]).hex(' ')}, "
                          f"not {FILE_MAGIC.hex(' ')}; expected a Lytro .lfp or data.C.N file")
    body = int.from_bytes(buf[12:16], "big")
    if body != 0:
        raise FormatError(f"LFP header announces a {body}-byte body; F01 files have none, so this is not one")


def _scan(buf: memoryview, *, verify: bool, problems: list[str] | None) -> Iterator[tuple[Section, bool]]:
    """Yield each section with whether its SHA-1 matches.

    With ``problems`` given, a damaged file is reported there and the scan stops at the
    first unreadable point instead of raising; checksum mismatches do not stop it.
    """
    pos = len(FILE_HEADER)
    end = len(buf)
    while True:
        # Between sections only NUL padding may sit; some writers pad differently, so skip it all.
        while pos < end:
            chunk = bytes(buf[pos:pos + 4096])
            rest = chunk.lstrip(b"\x00")
            pos += len(chunk) - len(rest)
            if rest:
                break
        if pos >= end:
            return
        try:
            section = _read_section(buf, pos)
        except FormatError as exc:
            if problems is None:
                raise
            problems.append(str(exc))
            return
        ok = True
        if verify:
            ok = sha1_ref(section.data) == section.sha1
            if not ok:
                msg = (f"{section.kind} section {section.sha1} at offset {pos}: data SHA-1 is "
                       f"{sha1_ref(section.data)}; the file is corrupted, copy it from the camera again")
                if problems is None:
                    raise ChecksumError(msg)
                problems.append(msg)
        yield section, ok
        pos = section.offset + SECTION_HEADER_BYTES + section.length


def _read_section(buf: memoryview, pos: int) -> Section:
    end = len(buf)
    magic = bytes(buf[pos:pos + 8])
    kind = _KIND_OF_MAGIC.get(magic)
    if kind is None:
        if len(magic) < 8 and (LFM_MAGIC.startswith(magic) or LFC_MAGIC.startswith(magic)):
            raise TruncatedFileError(f"the file ends at byte {end}, inside a section header at offset {pos}")
        raise FormatError(f"no LFM/LFC section magic at offset {pos} (found {magic.hex(' ')}); "
                          "the file is damaged or not an LFP container")
    if pos + SECTION_HEADER_BYTES > end:
        raise TruncatedFileError(f"the file ends at byte {end}, inside the 96-byte header of the "
                                 f"{kind} section at offset {pos}; the download was cut short")
    # Lytro's own reader takes bytes 8-15 as one big-endian int64 (the high word is zero).
    length = int.from_bytes(buf[pos + 8:pos + 16], "big", signed=True)
    if length < 0:
        raise FormatError(f"{kind} section at offset {pos} declares a negative length ({length})")
    ref_field = bytes(buf[pos + 16:pos + SECTION_HEADER_BYTES])
    ref = ref_field.rstrip(b"\x00").decode("ascii", errors="replace")
    if not _REF_RE.fullmatch(ref) or ref_field[45:].strip(b"\x00"):
        raise FormatError(f"{kind} section at offset {pos} has ref {ref_field[:45]!r}, not 'sha1-' "
                          "and 40 lowercase hex digits padded with NULs; the file is damaged")
    start = pos + SECTION_HEADER_BYTES
    if start + length > end:
        raise TruncatedFileError(f"{kind} section {ref} at offset {pos} announces {length} bytes, but the "
                                 f"file ends {end - start} bytes into it; the download was cut short")
    return Section(kind=kind, sha1=ref, offset=pos, data=buf[start:start + length])


def _toc_of(sections: Sequence[Section]) -> dict:
    lfms = [s for s in sections if s.kind == "LFM"]
    if not lfms:
        raise MissingSectionError("the container has no LFM (table of contents) section; "
                                  "the file is damaged or not a Lytro picture or bundle")
    if len(lfms) > 1:
        raise FormatError(f"the container has {len(lfms)} LFM sections (at offsets "
                          f"{', '.join(str(s.offset) for s in lfms)}); expected one table of contents")
    toc = parse_json(lfms[0].data, what=f"LFM table of contents {lfms[0].sha1}")
    if not isinstance(toc, dict):
        raise MetadataError(f"LFM table of contents {lfms[0].sha1} is a JSON {type(toc).__name__}, not an object")
    return toc


def read_container(data: bytes | bytearray | memoryview, *, verify: bool = True) -> LfpContainer:
    """Parse an LFP container.

    Parameters
    ----------
    data : bytes-like
        The whole file. Section data are memoryviews into it (no copies).
    verify : bool
        Check each section's SHA-1 against its ref.

    Returns
    -------
    LfpContainer

    Raises
    ------
    FormatError
        Not an LFP file, or bytes that are no section header.
    TruncatedFileError
        The file ends inside the header or a section.
    ChecksumError
        A section's SHA-1 differs from its ref (with ``verify``).
    MissingSectionError
        No LFM section.
    MetadataError
        The LFM is not a JSON object.
    """
    buf = memoryview(data).cast("B") if not isinstance(data, memoryview) or data.format != "B" else data
    if not buf.readonly:
        buf = memoryview(bytes(buf))  # sections must not change under their checked SHA-1
    _check_file_header(buf)
    sections = [s for s, _ in _scan(buf, verify=verify, problems=None)]
    return LfpContainer(sections=sections, toc=_toc_of(sections))


def read_container_file(path: str | Path, *, verify: bool = True) -> LfpContainer:
    """`read_container` on the bytes of the file at ``path``."""
    return read_container(Path(path).read_bytes(), verify=verify)


def inspect_container(data: bytes | bytearray | memoryview) -> ContainerReport:
    """Read as much of a possibly damaged container as can be read, without raising.

    Every section readable is listed with whether its SHA-1 checks out; truncation, stray
    bytes, a bad or missing table of contents and TOC refs without a section go to
    ``problems`` / ``missing_refs``.
    """
    report = ContainerReport()
    buf = memoryview(bytes(data))
    try:
        _check_file_header(buf)
    except FormatError as exc:
        report.problems.append(str(exc))
        return report
    sections = []
    for section, ok in _scan(buf, verify=True, problems=report.problems):
        sections.append(section)
        report.sections.append(SectionReport(section.kind, section.sha1, section.offset, section.length, ok))
    try:
        report.toc = _toc_of(sections)
    except FormatError as exc:
        report.problems.append(str(exc))
        return report
    report.container = LfpContainer(sections, report.toc)
    report.missing_refs = report.container.missing_refs()
    for path, ref in report.missing_refs:
        report.problems.append(f"{path} names section {ref}, which is not in the file")
    return report


def section_bytes(kind: str, data: bytes | bytearray | memoryview, *, ref: str | None = None) -> bytes:
    """One serialized section: 96-byte header, data, NUL padding to 16 bytes.

    ``ref`` defaults to `sha1_ref` of ``data``; give it only to re-write a read section as is.
    """
    magic = _MAGIC_OF_KIND.get(kind)
    if magic is None:
        raise ValueError(f"section kind must be 'LFM' or 'LFC', not {kind!r}")
    ref = sha1_ref(data) if ref is None else ref
    ref_field = ref.encode("ascii")
    if len(ref_field) > REF_FIELD_BYTES:
        raise ValueError(f"section ref {ref!r} is longer than {REF_FIELD_BYTES} bytes")
    pad = -len(data) % ALIGNMENT
    return b"".join((magic, len(data).to_bytes(8, "big"), ref_field.ljust(REF_FIELD_BYTES, b"\x00"),
                     bytes(data), b"\x00" * pad))


def container_bytes(sections: Sequence[Section]) -> bytes:
    """Serialize sections in the given order behind a file header (re-writes a read file byte for byte)."""
    return FILE_HEADER + b"".join(section_bytes(s.kind, s.data, ref=s.sha1) for s in sections)


def build_container(toc: dict, payloads: Sequence[bytes | bytearray | memoryview]) -> bytes:
    """A new container: the LFM holding ``toc`` first, then one LFC per payload (F01 order).

    The TOC must refer to the payloads by `sha1_ref`; identical payloads are stored once.

    Raises
    ------
    MissingSectionError
        If a ``...Ref`` in ``toc`` names none of the payloads (the file would be unreadable).
    """
    refs = {}
    for payload in payloads:
        refs.setdefault(sha1_ref(payload), payload)
    dangling = [(path, ref) for path, ref in iter_refs(toc) if ref not in refs]
    if dangling:
        raise MissingSectionError(
            "the table of contents names sections not among the payloads: "
            + ", ".join(f"{p} = {r}" for p, r in dangling))
    parts = [FILE_HEADER, section_bytes("LFM", json_bytes(toc))]
    parts.extend(section_bytes("LFC", payload, ref=ref) for ref, payload in refs.items())
    return b"".join(parts)
