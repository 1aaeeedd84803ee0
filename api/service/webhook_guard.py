"""Where a webhook may be sent: no loopback, private, link-local or other internal address.

A webhook URL is chosen by a user and fetched by the server, so without a guard it is a
way into the server's own network (the cloud metadata service at 169.254.169.254, a
database on 10.x, an admin page on localhost). Unless the operator allows it
(``GLINT_WEBHOOK_ALLOW_PRIVATE``), an address that is not a public unicast one is
refused: at creation when the URL names it literally (or says ``localhost``), and at
delivery for every address the host name resolves to; the delivery then connects to
the address that was checked (:func:`resolve_public`), so a name that resolves
differently a moment later (DNS rebinding) cannot slip past the check.
"""

from __future__ import annotations

import ipaddress
import re
import socket
from urllib.parse import SplitResult, urlsplit

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address

MAX_URL_LENGTH = 2048
SCHEMES = ("http", "https")
_CGNAT = ipaddress.ip_network("100.64.0.0/10")
_NAT64 = ipaddress.ip_network("64:ff9b::/96")
# inet_aton reads "127.1", "0x7f000001" and "2130706433" as 127.0.0.1, and so do resolvers
_LEGACY_IPV4 = re.compile(r"^(0x[0-9a-f]+|[0-9]+)(\.(0x[0-9a-f]+|[0-9]+)){0,3}$", re.IGNORECASE)


class ForbiddenAddressError(ValueError):
    """The URL's host is, or resolves to, an address the settings forbid."""


class UnresolvableHostError(OSError):
    """The host name does not resolve (now): worth trying again later."""


def forbidden_reason(ip: IPAddress) -> str | None:
    """Why ``ip`` is not a public unicast address (``"loopback"``, ...), or None if it is.

    IPv6 forms that carry an IPv4 address (IPv4-mapped ``::ffff:a.b.c.d``, 6to4, NAT64)
    are judged by the address they carry.
    """
    if isinstance(ip, ipaddress.IPv6Address):
        inner = ip.ipv4_mapped or ip.sixtofour
        if inner is None and ip in _NAT64:
            inner = ipaddress.IPv4Address(int(ip) & 0xFFFFFFFF)
        if inner is not None:
            return forbidden_reason(inner)
        if ip.is_site_local:
            return "site-local"
    checks = (
        (ip.is_unspecified, "unspecified"),
        (ip.is_loopback, "loopback"),
        (ip.is_link_local, "link-local"),
        (ip in _CGNAT, "shared (CGNAT)"),
        (ip.is_multicast, "multicast"),
        (ip.is_private, "private"),
        (ip.is_reserved, "reserved"),
        (not ip.is_global, "non-public"),
    )
    return next((why for bad, why in checks if bad), None)


def literal_address(host: str) -> IPAddress | None:
    """The address a URL host names literally (``[::1]`` as ``::1``, ``127.1`` as
    ``127.0.0.1``), or None for a host name."""
    host = host.strip("[]")
    try:
        return ipaddress.ip_address(host)
    except ValueError:
        pass
    if _LEGACY_IPV4.match(host):
        try:
            return ipaddress.IPv4Address(socket.inet_aton(host))
        except OSError:
            return None
    return None


def is_localhost(host: str) -> bool:
    """``localhost`` and its sub-domains, which resolve to loopback (RFC 6761)."""
    name = host.rstrip(".").lower()
    return name == "localhost" or name.endswith(".localhost")


def split_url(url: str) -> SplitResult:
    """``url`` taken apart, or ValueError saying what is wrong with it (users read it)."""
    if len(url) > MAX_URL_LENGTH:
        raise ValueError(f"URL is longer than {MAX_URL_LENGTH} characters")
    if any(c.isspace() or ord(c) < 32 for c in url):
        raise ValueError("URL contains white space or control characters")
    parts = urlsplit(url)
    if parts.scheme.lower() not in SCHEMES:
        raise ValueError(f"URL scheme must be http or https, not {parts.scheme or 'none'!r}")
    if not parts.hostname:
        raise ValueError("URL has no host")
    try:
        parts.port  # noqa: B018 (raises on a port that is not a number in range)
    except ValueError:
        raise ValueError("URL port is not a number from 0 to 65535") from None
    return parts


def check_literal(url: str, *, allow_private: bool) -> None:
    """At creation: refuse a URL whose host is ``localhost`` or a literal address the
    settings forbid (a host name is judged at delivery, when it is resolved)."""
    host = split_url(url).hostname or ""
    if allow_private:
        return
    if is_localhost(host):
        raise ForbiddenAddressError(
            f"'{host}' is a loopback name; webhooks go to public addresses only"
        )
    ip = literal_address(host)
    why = forbidden_reason(ip) if ip is not None else None
    if why is not None:
        raise ForbiddenAddressError(
            f"{ip} is a {why} address; webhooks go to public addresses only"
        )


def resolve_public(host: str, port: int, *, allow_private: bool) -> IPAddress:
    """The address to connect to for ``host``: every address it resolves to is checked
    (one forbidden address refuses the host: a name must not point inside at all).

    Raises :class:`ForbiddenAddressError` (final) or :class:`UnresolvableHostError`
    (transient).
    """
    if not allow_private and is_localhost(host):
        raise ForbiddenAddressError(f"'{host}' is a loopback name")
    literal = literal_address(host)
    if literal is not None:
        found = [literal]
    else:
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except (socket.gaierror, UnicodeError) as exc:
            raise UnresolvableHostError(f"cannot resolve '{host}': {exc}") from None
        # scope ids ("fe80::1%eth0") are cut: only the address itself is judged
        found = [ipaddress.ip_address(str(info[4][0]).split("%")[0]) for info in infos]
        if not found:
            raise UnresolvableHostError(f"'{host}' resolves to no address")
    if not allow_private:
        for ip in found:
            why = forbidden_reason(ip)
            if why is not None:
                shown = host if literal is not None else f"'{host}' resolves to {ip}, which"
                raise ForbiddenAddressError(f"{shown} is a {why} address")
    return found[0]
