"""``kgadapt certs``: the TLS certificates of one robot for mutual TLS between its processes.

The shipped Zenoh configurations (``deploy/zenoh/*.json5``) use mutual TLS:
every process presents a certificate signed by the robot's certificate
authority (CA), and the router's access control knows a process by the
common name (CN) of its certificate. This command writes, into one directory,
exactly the files those configurations reference under ``/etc/kgadapt/tls/``::

    ca.pem                      the CA certificate (every host needs it)
    ca-key.pem                  the CA's private key (keep it offline; 0600)
    <robot>-knowledge.pem/-key.pem   the router in the knowledge service (SAN: the names hosts dial)
    <robot>-onboard.pem/-key.pem     the onboard agent (host monitor, deployer, manager, flight bridge)
    <robot>-remote.pem/-key.pem      the remote agent
    <robot>-onboard-detector.pem/-key.pem  the detectors the onboard deployer starts
    <robot>-remote-detector.pem/-key.pem   the detectors the remote deployer starts
    <robot>-operator.pem/-key.pem    people's tools (kgadapt deploy / ask / why)

Keys are ECDSA P-256, written with mode 0600 (certificates 0644), each file
replaced atomically. An existing CA is never overwritten unless ``--force``
is given; ``--use-ca`` issues more certificates with it instead (another
robot's, whose CNs the router lists as ``other-robots``, or a host renamed).

    kgadapt certs ./tls --robot quad1 --router-address knowledge.quad1.local --router-address 10.0.0.2
    kgadapt certs ./tls --robot quad2 --role onboard --use-ca      # quad2-onboard, same CA

Needs the ``cryptography`` package (imported when the command runs).
"""

from __future__ import annotations

import argparse
import datetime
import ipaddress
import json
import os
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

from kgadapt.shared import keys
from kgadapt.shared.errors import ConfigError
from kgadapt.shared.keys import DEFAULT_ROBOT

if TYPE_CHECKING:  # cryptography is imported where used: most commands never need it
    from cryptography import x509
    from cryptography.hazmat.primitives.asymmetric.types import PrivateKeyTypes, PublicKeyTypes

# A detector has its own identity, not its host's: the router lets it publish detections, serve its
# reconfiguration and read its configuration, nothing else (deploy/zenoh/router.json5).
ROLES = ("knowledge", "onboard", "remote", "operator", "onboard-detector", "remote-detector")
CA_CERT = "ca.pem"
CA_KEY = "ca-key.pem"
KEY_MODE = 0o600
CERT_MODE = 0o644
_DNS_LABEL = re.compile(r"^(?!-)[A-Za-z0-9-]{1,63}(?<!-)$")


@dataclass(frozen=True, kw_only=True)
class CertSettings:
    """What ``make_certificates`` writes. Empty ``router_addresses`` means the defaults."""

    directory: Path
    robot: str = DEFAULT_ROBOT
    roles: tuple[str, ...] = ROLES
    router_addresses: tuple[str, ...] = ()
    addresses: Mapping[str, tuple[str, ...]] = field(default_factory=dict)  # role -> extra SANs
    days: int = 825  # leaf certificates (the longest lifetime common clients accept)
    ca_days: int = 3650
    use_ca: bool = False
    force: bool = False

    def __post_init__(self) -> None:
        keys.check_name(self.robot, "robot name")
        if not self.roles:
            raise ConfigError("no role to issue a certificate for")
        for role in self.roles:
            if role not in ROLES:
                raise ConfigError(f"unknown role {role!r}: use {', '.join(ROLES)}")
        for role in self.addresses:
            if role not in ROLES:
                raise ConfigError(f"address given for unknown role {role!r}: use {', '.join(ROLES)}")
        for what, days in (("--days", self.days), ("--ca-days", self.ca_days)):
            if not isinstance(days, int) or isinstance(days, bool) or days < 1:
                raise ConfigError(f"{what} {days!r}: a whole number of days, at least 1")
        if self.use_ca and self.force:
            raise ConfigError("--use-ca keeps the existing CA and --force replaces it: give one of them")

    def common_name(self, role: str) -> str:
        """The CN the router's access control knows this role by (``<robot>-<role>``)."""
        return f"{self.robot}-{role}"

    def sans(self, role: str) -> tuple[str, ...]:
        """The DNS names and IP addresses this role's certificate is valid for."""
        if role == "knowledge":
            # knowledge.<robot>.local always: it is the name the shipped client configs dial
            # (deploy/zenoh/onboard.json5, remote.json5); --router-address adds to it.
            base = (f"knowledge.{self.robot}.local", *(self.router_addresses or ("localhost", "127.0.0.1")))
        else:
            base = (f"{role}.{self.robot}.local",)
        return tuple(dict.fromkeys((*base, *self.addresses.get(role, ()))))


@dataclass(frozen=True)
class IssuedCertificate:
    """One certificate written: who it names, where it is, what it is valid for."""

    role: str
    common_name: str
    certificate: Path
    private_key: Path
    sans: tuple[str, ...]
    not_after: str
    sha256: str

    def as_dict(self) -> dict[str, Any]:
        return {"role": self.role, "common_name": self.common_name, "certificate": str(self.certificate),
                "private_key": str(self.private_key), "sans": list(self.sans), "not_after": self.not_after,
                "sha256": self.sha256}


@dataclass(frozen=True)
class CertReport:
    """What one run did: the CA (made or reused) and the certificates issued."""

    directory: Path
    ca_certificate: Path
    ca_created: bool
    issued: tuple[IssuedCertificate, ...]

    def as_dict(self) -> dict[str, Any]:
        return {"directory": str(self.directory), "ca_certificate": str(self.ca_certificate),
                "ca_created": self.ca_created, "issued": [c.as_dict() for c in self.issued]}


def check_address(address: str) -> str:
    """``address`` if it is an IP address or a DNS name (``*.`` wildcard allowed first), else ConfigError."""
    if not isinstance(address, str) or not address:
        raise ConfigError(f"address {address!r}: give a DNS name or an IP address")
    try:
        ipaddress.ip_address(address)
        return address
    except ValueError:
        pass
    labels = address.split(".")
    if labels[0] == "*" and len(labels) > 1:
        labels = labels[1:]
    if len(address) > 253 or not all(_DNS_LABEL.match(label) for label in labels):
        raise ConfigError(f"address {address!r} is neither an IP address nor a DNS name")
    return address


class CertificateAuthority:
    """A CA key and certificate; ``issue`` signs leaf certificates. Use ``create`` or ``load``."""

    def __init__(self, key: Any, certificate: Any) -> None:
        self.key = key
        self.certificate = certificate

    @classmethod
    def create(cls, name: str, *, days: int) -> "CertificateAuthority":
        """A new self-signed CA (ECDSA P-256) that may sign leaf certificates only (path length 0)."""
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import NameOID

        key = ec.generate_private_key(ec.SECP256R1())
        subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
        now = _now()
        certificate = (
            x509.CertificateBuilder()
            .subject_name(subject).issuer_name(subject)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(_key_usage(ca=True), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256())
        )
        return cls(key, certificate)

    @classmethod
    def load(cls, directory: Path) -> "CertificateAuthority":
        """The CA in ``directory`` (``ca.pem``, ``ca-key.pem``); ConfigError naming what is wrong."""
        from cryptography import x509
        from cryptography.hazmat.primitives import serialization

        cert_path, key_path = directory / CA_CERT, directory / CA_KEY
        try:
            certificate = x509.load_pem_x509_certificate(cert_path.read_bytes())
        except OSError as exc:
            raise ConfigError(f"cannot read the CA certificate {cert_path}: {exc.strerror or exc}") from exc
        except ValueError as exc:
            raise ConfigError(f"{cert_path} is not a PEM certificate: {exc}") from exc
        try:
            key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        except OSError as exc:
            raise ConfigError(f"cannot read the CA key {key_path} (needed to issue with --use-ca): "
                              f"{exc.strerror or exc}") from exc
        except (ValueError, TypeError) as exc:
            raise ConfigError(f"{key_path} is not an unencrypted PEM private key: {exc}") from exc
        try:
            constraints = certificate.extensions.get_extension_for_class(x509.BasicConstraints).value
        except x509.ExtensionNotFound:
            constraints = None
        if constraints is None or not constraints.ca:
            raise ConfigError(f"{cert_path} is not a CA certificate (no basicConstraints CA:TRUE)")
        if _public_bytes(key.public_key()) != _public_bytes(certificate.public_key()):
            raise ConfigError(f"{key_path} is not the key of {cert_path}")
        return cls(key, certificate)

    def issue(self, common_name: str, sans: Sequence[str], *, days: int) -> tuple[Any, Any]:
        """A new key and a certificate for ``common_name`` valid for ``sans``, for servers and clients."""
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

        key = ec.generate_private_key(ec.SECP256R1())
        names: list[x509.GeneralName] = []
        for address in sans:
            try:
                names.append(x509.IPAddress(ipaddress.ip_address(address)))
            except ValueError:
                names.append(x509.DNSName(address))
        now = _now()
        not_after = min(now + datetime.timedelta(days=days), self.certificate.not_valid_after_utc)
        certificate = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
            .issuer_name(self.certificate.subject)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(not_after)
            .add_extension(x509.SubjectAlternativeName(names), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(_key_usage(ca=False), critical=True)
            # With mutual TLS every process is a client, and the router a server too.
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(self.key.public_key()), critical=False)
            .sign(self.key, hashes.SHA256())
        )
        return key, certificate


def make_certificates(settings: CertSettings) -> CertReport:
    """Make (or reuse, with ``use_ca``) the CA in ``settings.directory`` and issue each role's certificate."""
    from kgadapt.shared.extras import require

    require("cryptography", extra="certs", what="kgadapt certs")
    directory = Path(settings.directory)
    sans = {role: tuple(check_address(a) for a in settings.sans(role)) for role in settings.roles}
    existing = [name for name in (CA_CERT, CA_KEY) if (directory / name).exists()]
    if settings.use_ca:
        if CA_CERT not in existing:
            raise ConfigError(f"--use-ca: there is no CA in {directory} ({CA_CERT} is missing)")
        ca = CertificateAuthority.load(directory)
        created = False
    else:
        if existing and not settings.force:
            raise ConfigError(
                f"{directory / existing[0]} already exists: pass --use-ca to issue certificates with that CA, "
                "or --force to replace it (every certificate it signed stops being accepted)")
        ca = CertificateAuthority.create(f"kgadapt {settings.robot} CA", days=settings.ca_days)
        created = True
    try:
        if not directory.exists():
            directory.mkdir(mode=0o700, parents=True)
    except OSError as exc:
        raise ConfigError(f"cannot create {directory}: {exc.strerror or exc}") from exc
    if created:
        # The key first: a ca.pem without its key would be a CA nobody can issue with.
        _write(directory / CA_KEY, _key_pem(ca.key), KEY_MODE)
        _write(directory / CA_CERT, _cert_pem(ca.certificate), CERT_MODE)
    issued = []
    for role in settings.roles:
        cn = settings.common_name(role)
        key, certificate = ca.issue(cn, sans[role], days=settings.days)
        key_path, cert_path = directory / f"{cn}-key.pem", directory / f"{cn}.pem"
        _write(key_path, _key_pem(key), KEY_MODE)
        _write(cert_path, _cert_pem(certificate), CERT_MODE)
        issued.append(IssuedCertificate(
            role=role, common_name=cn, certificate=cert_path, private_key=key_path, sans=sans[role],
            not_after=certificate.not_valid_after_utc.isoformat(timespec="seconds"),
            sha256=_fingerprint(certificate)))
    return CertReport(directory=directory, ca_certificate=directory / CA_CERT, ca_created=created,
                      issued=tuple(issued))


# -- command line ---------------------------------------------------------------


def register(subparsers: Any) -> None:
    """Add ``kgadapt certs``."""
    parser = subparsers.add_parser(
        "certs",
        help="make a robot's TLS certificate authority and certificates",
        description="Make a certificate authority and one certificate per identity the shipped Zenoh "
        "configurations use (<robot>-knowledge, -onboard, -remote, -operator), as PEM files in DIR named as "
        "deploy/zenoh/*.json5 expect them under /etc/kgadapt/tls/. Keys are written 0600. An existing CA "
        "is kept: --use-ca issues with it, --force replaces it.",
    )
    parser.add_argument("directory", metavar="DIR", help="where to write the PEM files (created 0700 if missing)")
    parser.add_argument("--robot", default=DEFAULT_ROBOT,
                        help=f"robot name: the CNs are <robot>-<role> (default {DEFAULT_ROBOT})")
    parser.add_argument("--role", action="append", choices=ROLES, metavar="ROLE",
                        help=f"issue only this role's certificate (repeatable; default all: {', '.join(ROLES)})")
    parser.add_argument("--router-address", action="append", metavar="NAME",
                        help="DNS name or IP address the hosts dial the router by, for the knowledge certificate's "
                        "SAN, besides knowledge.<robot>.local, which the shipped configs dial (repeatable; default: "
                        "localhost, 127.0.0.1)")
    parser.add_argument("--address", action="append", default=[], metavar="ROLE=NAME",
                        help="an extra SAN for one role's certificate, e.g. remote=10.0.0.3 (repeatable)")
    parser.add_argument("--days", type=int, default=825, help="validity of the certificates in days (default 825)")
    parser.add_argument("--ca-days", type=int, default=3650, help="validity of a new CA in days (default 3650)")
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--use-ca", action="store_true", help="issue with the CA already in DIR")
    which.add_argument("--force", action="store_true",
                       help="replace an existing CA (certificates it signed are no longer accepted)")
    parser.add_argument("--json", action="store_true", help="print what was written as JSON")
    parser.set_defaults(func=run)


def settings_from_args(args: argparse.Namespace) -> CertSettings:
    """CertSettings from the parsed ``kgadapt certs`` flags."""
    addresses: dict[str, tuple[str, ...]] = {}
    for entry in args.address:
        role, sep, name = entry.partition("=")
        if not sep or not name:
            raise ConfigError(f"--address {entry!r}: write ROLE=NAME, e.g. remote=10.0.0.3")
        addresses[role] = (*addresses.get(role, ()), name)
    return CertSettings(
        directory=Path(args.directory).expanduser(), robot=args.robot,
        roles=tuple(dict.fromkeys(args.role or ROLES)), router_addresses=tuple(args.router_address or ()),
        addresses=addresses, days=args.days, ca_days=args.ca_days, use_ca=args.use_ca, force=args.force)


def run(args: argparse.Namespace) -> int:
    report = make_certificates(settings_from_args(args))
    if args.json:
        print(json.dumps(report.as_dict(), indent=2))
        return 0
    what = "made" if report.ca_created else "reused"
    print(f"CA {what}: {report.ca_certificate} (keep {report.directory / CA_KEY} offline)")
    for cert in report.issued:
        print(f"{cert.common_name}: {cert.certificate}, {cert.private_key} (SAN {', '.join(cert.sans)}; "
              f"until {cert.not_after})")
    print(f"Copy {CA_CERT} and each host's <name>.pem and <name>-key.pem to /etc/kgadapt/tls/ on that host "
          "(key owned by the kgadapt user, mode 0600).")
    return 0


# -- helpers -------------------------------------------------------------------


def _now() -> datetime.datetime:
    return datetime.datetime.now(datetime.timezone.utc)


def _key_usage(*, ca: bool) -> Any:
    from cryptography import x509

    return x509.KeyUsage(
        digital_signature=True, content_commitment=False, key_encipherment=False, data_encipherment=False,
        key_agreement=False, key_cert_sign=ca, crl_sign=ca, encipher_only=False, decipher_only=False)


def _key_pem(key: PrivateKeyTypes) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _cert_pem(certificate: x509.Certificate) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return certificate.public_bytes(serialization.Encoding.PEM)


def _public_bytes(public_key: PublicKeyTypes) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return public_key.public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)


def _fingerprint(certificate: x509.Certificate) -> str:
    from cryptography.hazmat.primitives import hashes

    return certificate.fingerprint(hashes.SHA256()).hex(":")


def _write(path: Path, data: bytes, mode: int) -> None:
    """Write ``data`` to ``path`` atomically with ``mode`` (a key is never readable by others, even briefly)."""
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")  # created 0600
        try:
            with os.fdopen(fd, "wb") as out:
                out.write(data)
                out.flush()
                os.fsync(out.fileno())
            os.chmod(tmp, mode)
            os.replace(tmp, path)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise
    except OSError as exc:
        raise ConfigError(f"cannot write {path}: {exc.strerror or exc}") from exc
