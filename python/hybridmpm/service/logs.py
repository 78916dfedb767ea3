"""Session ids out of the logs.

A session id is the only credential a session has, and request paths carry
it (``/v1/sessions/<id>/step``). :class:`RedactSessionIds` cuts every id in
a log record — its message, its arguments (uvicorn's access log formats
them itself) and its traceback — to its first :data:`SHOWN_ID_CHARS`
characters and ``…``: enough to correlate lines, useless to take over a
session. :func:`install_log_filters` puts it on the service's and uvicorn's
loggers.
"""

from __future__ import annotations

import logging
import re
from typing import Any

#: Characters of a session id kept in log lines (of 32).
SHOWN_ID_CHARS = 6
#: Loggers whose records are redacted.
LOGGERS = ("hybridmpm.service", "uvicorn", "uvicorn.error", "uvicorn.access", "fastapi", "asyncio")
# a path segment after /sessions/ (a URL-encoded one too), and "session <id>" in prose
_PATTERNS = [
    re.compile(r"(sessions(?:/|%2F))([A-Za-z0-9_-]{" + str(SHOWN_ID_CHARS) + r"})[A-Za-z0-9_%-]+", re.IGNORECASE),
    re.compile(r"(session[ =:]+)([A-Za-z0-9_-]{" + str(SHOWN_ID_CHARS) + r"})[A-Za-z0-9_-]{10,}", re.IGNORECASE),
]


def redact(text: str) -> str:
    """``text`` with every session id cut to its first :data:`SHOWN_ID_CHARS` characters and ``…``."""
    for p in _PATTERNS:
        text = p.sub(lambda m: f"{m.group(1)}{m.group(2)}…", text)
    return text


def _redact_arg(a: Any) -> Any:
    return redact(a) if isinstance(a, str) else a


class RedactSessionIds(logging.Filter):
    """A logging filter that redacts session ids in place (the record is always kept)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(_redact_arg(a) for a in record.args)
        elif isinstance(record.args, dict):
            record.args = {k: _redact_arg(v) for k, v in record.args.items()}
        if record.exc_info and not record.exc_text:
            record.exc_text = logging.Formatter().formatException(record.exc_info)
        if record.exc_text:
            record.exc_text = redact(record.exc_text)
        return True


_FILTER = RedactSessionIds()


def install_log_filters() -> None:
    """Put the redacting filter on :data:`LOGGERS` (once each; call again
    after a logging configuration replaced them)."""
    for name in LOGGERS:
        logger = logging.getLogger(name)
        if _FILTER not in logger.filters:
            logger.addFilter(_FILTER)


__all__ = ["LOGGERS", "SHOWN_ID_CHARS", "RedactSessionIds", "install_log_filters", "redact"]
