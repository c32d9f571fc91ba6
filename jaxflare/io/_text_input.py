"""Reading input files safely: regular files of a bounded size, decoded as text with errors that
name the file and the line.

Every reader of a user's file (lens TOML, Zemax, the lens formats of other tools, scenes) goes
through :func:`read_input_bytes`, so a directory, a device such as ``/dev/zero``, a FIFO or a
multi-gigabyte file is refused before anything is read into memory, and through
:func:`decode_text` (or its own decoder, as the Zemax reader), so a binary file is "not a text
file" rather than a parse error somewhere inside it.
"""

from __future__ import annotations

import codecs
import os
import stat

MAX_INPUT_BYTES = 16 * 2**20
"""Largest input file read (16 MiB): the biggest real lens or scene files are a few hundred kB."""

_ALLOWED_CONTROL = frozenset("\t\n\r\x0c\x1a")


def read_input_bytes(path: str | os.PathLike, what: str, error: type[Exception], max_bytes: int = MAX_INPUT_BYTES) -> bytes:
    """The bytes of ``path``, a regular file of at most ``max_bytes``.

    Raises ``FileNotFoundError`` for a missing file and ``error(message)`` (the caller's error type,
    e.g. :class:`~jaxflare.optics.LensFormatError`) for a directory, a device, a FIFO or socket, an
    unreadable file, or one larger than ``max_bytes``; ``what`` names the file's role in messages.
    """
    name = os.fspath(path)
    try:
        info = os.stat(name)
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} not found: {name}") from None
    except OSError as failure:
        raise error(f"{name}: cannot read the {what}: {failure.strerror}") from None
    if stat.S_ISDIR(info.st_mode):
        raise error(f"{name}: is a directory, not a {what}")
    if not stat.S_ISREG(info.st_mode):
        raise error(f"{name}: is not a regular file (a device, pipe or socket), so it is not read as a {what}")
    if info.st_size > max_bytes:
        raise error(f"{name}: {info.st_size:,} bytes is too large for a {what} (at most {max_bytes // 2**20} MiB)")
    try:
        with open(name, "rb") as handle:
            data = handle.read(max_bytes + 1)
    except OSError as failure:
        raise error(f"{name}: cannot read the {what}: {failure.strerror}") from None
    if len(data) > max_bytes:
        raise error(f"{name}: too large for a {what} (more than {max_bytes // 2**20} MiB)")
    return data


def check_text(text: str, name: str, what: str, error: type[Exception]) -> str:
    """``text`` if it holds no control characters other than tab, line breaks and form feed, else
    ``error`` naming the line of the first one ("not a text file")."""
    for index, character in enumerate(text):
        if character < " " and character not in _ALLOWED_CONTROL:
            line = text.count("\n", 0, index) + 1
            raise error(f"{name}:{line}: not a text file (control character U+{ord(character):04X}); is this really a {what}?")
    return text


def decode_text(data: bytes, name: str, what: str, error: type[Exception]) -> str:
    """``data`` decoded as UTF-8 (a byte-order mark is dropped; UTF-16 with a BOM is accepted too),
    checked by :func:`check_text`. A byte that is not UTF-8 is ``error`` naming its line."""
    if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        try:
            text = data.decode("utf-16")
        except UnicodeDecodeError as failure:
            raise error(f"{name}: not a text file (UTF-16 decoding failed: {failure.reason})") from None
        return check_text(text.lstrip("\ufeff"), name, what, error)
    data = data.removeprefix(codecs.BOM_UTF8)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as failure:
        line = data.count(b"\n", 0, failure.start) + 1
        column = failure.start - (data.rfind(b"\n", 0, failure.start) + 1) + 1
        raise error(
            f"{name}:{line}: not UTF-8 text (byte 0x{data[failure.start]:02X} at column {column}); save the {what} as UTF-8"
        ) from None
    return check_text(text, name, what, error)


def read_text_file(path: str | os.PathLike, what: str, error: type[Exception], max_bytes: int = MAX_INPUT_BYTES) -> str:
    """:func:`read_input_bytes` then :func:`decode_text`."""
    name = os.fspath(path)
    return decode_text(read_input_bytes(name, what, error, max_bytes), name, what, error)
