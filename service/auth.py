"""Optional bearer-token authentication.

With no tokens configured every request is anonymous and all jobs belong to
the same (anonymous) owner. With tokens, every ``/v1`` request must send
``Authorization: Bearer <token>``; the job owner is a hash of the token, so a
job is only visible to the token that created it.
"""

from __future__ import annotations

import hashlib
import hmac

from bubsub.service.errors import APIError

__all__ = ["TokenAuth", "ANONYMOUS"]

#: owner of every job when authentication is off
ANONYMOUS = "anonymous"


class TokenAuth:
    """Checks bearer tokens in constant time.

    Parameters
    ----------
    tokens : sequence of str
        Accepted tokens; empty disables authentication.
    """

    def __init__(self, tokens=()):
        self._tokens = tuple(t.encode("utf-8") for t in tokens if t)

    @property
    def enabled(self) -> bool:
        """Whether requests must carry a token."""
        return bool(self._tokens)

    def owner(self, authorization: str | None) -> str:
        """The owner id of a request from its ``Authorization`` header.

        Parameters
        ----------
        authorization : str or None

        Returns
        -------
        str
            :data:`ANONYMOUS` when authentication is off, else a SHA-256
            digest of the token (tokens are never stored or logged).

        Raises
        ------
        APIError
            401 when the header is missing, malformed or the token unknown.
        """
        if not self.enabled:
            return ANONYMOUS
        challenge = {"WWW-Authenticate": 'Bearer realm="bubsub"'}
        scheme, _, token = (authorization or "").partition(" ")
        token = token.strip()
        if scheme.lower() != "bearer" or not token:
            raise APIError(401, "missing bearer token: send 'Authorization: Bearer <token>'",
                           "unauthorized", challenge)
        given = token.encode("utf-8", "surrogateescape")
        ok = False
        for known in self._tokens:  # no early exit: time does not depend on which token matched
            ok |= hmac.compare_digest(given, known)
        if not ok:
            raise APIError(401, "invalid bearer token", "unauthorized", challenge)
        return hashlib.sha256(given).hexdigest()
