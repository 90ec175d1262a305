"""``kgadapt certs``: the files the shipped configurations reference, with the names their access control knows."""

from __future__ import annotations

import ipaddress
import json
import re
import stat
import subprocess

import pytest
import zenoh
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from tests.conftest import REPO
from tests.security.conftest import ROBOT, ZENOH_DIR, kgadapt

SCRIPT = REPO / "deploy" / "tls" / "make-certs.sh"


def load(path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def common_name(cert: x509.Certificate) -> str:
    return cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value


def sans(cert: x509.Certificate) -> set[str]:
    names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    return {str(n.value) for n in names}


def referenced_tls_files() -> set[str]:
    found: set[str] = set()
    for path in ZENOH_DIR.glob("*.json5"):
        found |= set(re.findall(r"/etc/kgadapt/tls/([\w.-]+)", path.read_text()))
    return found


def router_subjects() -> dict[str, list[str]]:
    acl = json.loads(zenoh.Config.from_file(str(ZENOH_DIR / "router.json5")).get_json("access_control"))
    return {s["id"]: s.get("cert_common_names", []) for s in acl["subjects"]}


def test_the_command_writes_every_file_the_shipped_configurations_reference(tmp_path):
    result = kgadapt("certs", str(tmp_path / "tls"), "--json")
    report = json.loads(result.stdout)
    written = {p.name for p in (tmp_path / "tls").iterdir()}
    assert referenced_tls_files() <= written
    assert referenced_tls_files() >= {"ca.pem", "quad1-knowledge.pem", "quad1-onboard-key.pem", "quad1-remote.pem"}
    assert report["ca_created"] is True
    assert {c["common_name"] for c in report["issued"]} == {f"{ROBOT}-{r}" for r in (
        "knowledge", "onboard", "remote", "operator", "onboard-detector", "remote-detector")}


def test_the_common_names_are_the_subjects_the_router_grants_this_robots_rights_to(tmp_path):
    kgadapt("certs", str(tmp_path))
    issued = {common_name(load(p)) for p in tmp_path.glob("quad1-*.pem") if not p.name.endswith("-key.pem")}
    subjects = router_subjects()
    own = ("quad1-onboard", "quad1-remote", "quad1-knowledge", "quad1-operators",  # one subject per host
           "quad1-onboard-detectors", "quad1-remote-detectors")  # and per host's detectors
    assert set().union(*(subjects[s] for s in own)) == issued


def test_private_keys_are_written_0600_and_certificates_0644(tmp_path):
    kgadapt("certs", str(tmp_path / "tls"))
    files = list((tmp_path / "tls").iterdir())
    keys = [p for p in files if p.name.endswith("-key.pem")]
    assert len(keys) == 7  # the CA's and six identities'
    for path in files:
        mode = stat.S_IMODE(path.stat().st_mode)
        assert mode == (0o600 if path in keys else 0o644), f"{path.name} has mode {oct(mode)}"
    assert stat.S_IMODE((tmp_path / "tls").stat().st_mode) == 0o700
    assert not [p for p in files if p.name.startswith(".")]  # no temporary file left behind


def test_each_certificate_is_signed_by_the_ca_and_valid_for_the_addresses_given(tmp_path):
    kgadapt("certs", str(tmp_path), "--robot", "quad7", "--router-address", "knowledge.example.org",
            "--router-address", "10.0.0.2", "--address", "remote=10.0.0.3", "--days", "30")
    ca = load(tmp_path / "ca.pem")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is True
    for role in ("knowledge", "onboard", "remote", "operator"):
        cert = load(tmp_path / f"quad7-{role}.pem")
        cert.verify_directly_issued_by(ca)
        assert common_name(cert) == f"quad7-{role}"
        assert cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is False
        usages = set(cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value)
        assert usages == {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH}
        days = (cert.not_valid_after_utc - cert.not_valid_before_utc).days
        assert 29 <= days <= 30
    router = load(tmp_path / "quad7-knowledge.pem")
    assert sans(router) == {"knowledge.example.org", "10.0.0.2", "knowledge.quad7.local"}  # the name shipped configs dial
    ip_names = router.extensions.get_extension_for_class(x509.SubjectAlternativeName).value.get_values_for_type(
        x509.IPAddress)
    assert ip_names == [ipaddress.ip_address("10.0.0.2")]  # an IP SAN, not a DNS name "10.0.0.2"
    assert sans(load(tmp_path / "quad7-remote.pem")) == {"remote.quad7.local", "10.0.0.3"}


def test_the_router_certificate_is_valid_for_the_shipped_endpoint_by_default(tmp_path):
    kgadapt("certs", str(tmp_path))
    endpoints = json.loads(zenoh.Config.from_file(str(ZENOH_DIR / "onboard.json5")).get_json("connect/endpoints"))
    dialed = {e.split("/", 1)[1].rsplit(":", 1)[0] for e in endpoints}
    assert dialed <= sans(load(tmp_path / "quad1-knowledge.pem"))


def test_an_existing_ca_is_not_overwritten_without_force(tmp_path):
    kgadapt("certs", str(tmp_path))
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    result = kgadapt("certs", str(tmp_path), check=False)
    assert result.returncode == 1
    assert "ca" in result.stderr and "already exists" in result.stderr and "--force" in result.stderr
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_use_ca_issues_more_certificates_with_the_existing_ca_and_force_replaces_it(tmp_path):
    kgadapt("certs", str(tmp_path))
    ca_before = (tmp_path / "ca.pem").read_bytes()
    kgadapt("certs", str(tmp_path), "--robot", "quad2", "--role", "onboard", "--use-ca")
    assert (tmp_path / "ca.pem").read_bytes() == ca_before
    load(tmp_path / "quad2-onboard.pem").verify_directly_issued_by(load(tmp_path / "ca.pem"))
    assert not (tmp_path / "quad2-remote.pem").exists()  # only the role asked for
    kgadapt("certs", str(tmp_path), "--force")
    assert (tmp_path / "ca.pem").read_bytes() != ca_before
    with pytest.raises(Exception):  # the old CA's certificate no longer chains to the new CA
        load(tmp_path / "quad2-onboard.pem").verify_directly_issued_by(load(tmp_path / "ca.pem"))


def test_use_ca_refuses_a_directory_without_a_ca_or_with_a_key_that_does_not_match(tmp_path):
    result = kgadapt("certs", str(tmp_path / "empty"), "--use-ca", check=False)
    assert result.returncode == 1 and "ca.pem is missing" in result.stderr
    kgadapt("certs", str(tmp_path / "a"))
    kgadapt("certs", str(tmp_path / "b"))
    (tmp_path / "a" / "ca-key.pem").write_bytes((tmp_path / "b" / "ca-key.pem").read_bytes())
    result = kgadapt("certs", str(tmp_path / "a"), "--use-ca", check=False)
    assert result.returncode == 1 and "ca-key.pem is not the key of" in result.stderr


@pytest.mark.parametrize("args,named", [
    (["--robot", "quad/1"], "'quad/1'"),
    (["--robot", "quad1 ; rm -rf /"], "robot name"),
    (["--router-address", "not a name!"], "'not a name!'"),
    (["--address", "camera=10.0.0.9"], "'camera'"),
    (["--address", "remote"], "'remote'"),
    (["--days", "0"], "--days 0"),
    (["--use-ca", "--force"], "not allowed with"),
])
def test_bad_settings_are_refused_naming_the_offending_value_and_nothing_is_written(tmp_path, args, named):
    result = kgadapt("certs", str(tmp_path / "tls"), *args, check=False)
    assert result.returncode != 0
    assert named in result.stderr, result.stderr
    assert not (tmp_path / "tls").exists()


def test_the_shipped_script_is_a_wrapper_of_the_command_and_reuses_an_existing_ca(tmp_path):
    env = {"PATH": "/usr/bin:/bin", "KGADAPT": f"{REPO / '.venv' / 'bin' / 'python'} -m kgadapt"}
    run = lambda *a: subprocess.run(["bash", str(SCRIPT), *a], capture_output=True, text=True, timeout=60,  # noqa: E731
                                    cwd=REPO, env=env, check=True)
    run(str(tmp_path), "quad3", "knowledge.quad3.example", "192.168.7.1")
    ca = (tmp_path / "ca.pem").read_bytes()
    assert sans(load(tmp_path / "quad3-knowledge.pem")) == {"knowledge.quad3.example", "192.168.7.1", "knowledge.quad3.local"}
    run(str(tmp_path), "quad3")
    assert (tmp_path / "ca.pem").read_bytes() == ca  # reused, as the script always did
    load(tmp_path / "quad3-knowledge.pem").verify_directly_issued_by(load(tmp_path / "ca.pem"))
    assert sans(load(tmp_path / "quad3-knowledge.pem")) == {"knowledge.quad3.local", "localhost", "127.0.0.1"}
