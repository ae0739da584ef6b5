"""Security against the real `mpiflow serve`: the bearer token (no token or a wrong one gets
UNAUTHENTICATED and no sample; health stays open) and TLS (the right CA connects, another CA or
plaintext does not). Certificates come from the `openssl` command; the TLS tests are skipped
where it is missing."""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import grpc
import pytest

import mpiflow
from conftest import Server, real_binary

TOKEN = "py-s3cret-token-0123"


@pytest.fixture(scope="module")
def binary():
    if real_binary() is None:
        pytest.skip("target/release/mpiflow not built (set MPIFLOW_BIN)")


@pytest.fixture(scope="module")
def token_file(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("token") / "token"
    p.write_text(TOKEN + "\n")
    return p


@pytest.fixture(scope="module")
def token_server(binary, token_file):
    s = Server("real", extra=["--size", "64x48", "--workers", "2", "--auth-token-file", str(token_file)]).start()
    yield s
    s.stop()


def test_no_token_or_a_wrong_token_is_unauthenticated(token_server):
    for token, says in ((None, "missing bearer token"), ("wrong", "invalid bearer token")):
        with mpiflow.Client(token_server.address, token=token, timeout=30) as c:
            # health needs no token: the constructor waited for SERVING
            assert c.health(token_server.address) == "SERVING"
            with pytest.raises(grpc.RpcError) as e:
                c.info()
            assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED
            assert says in e.value.details()
            with pytest.raises(grpc.RpcError) as e:
                c.get_sample(0)
            assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED
            got = []
            with pytest.raises(mpiflow.MpiFlowError) as e:
                for s in c.stream(count=3, retry_timeout=5):
                    got.append(s)
            assert got == []
            assert "UNAUTHENTICATED" in str(e.value) and says in str(e.value)


def test_the_right_token_gets_samples(token_server):
    with mpiflow.Client(token_server.address, token=TOKEN, timeout=30) as c:
        assert [s.index for s in c.stream(count=3, seed=2)] == [0, 1, 2]
        assert c.get_sample(5, seed=2).index == 5
        assert c.info().datasets
    ds = mpiflow.MPIFlowDataset(token_server.address, token=TOKEN, count=2, prefetch=0)
    assert [s["index"] for s in ds] == [0, 1]
    bad = mpiflow.MPIFlowDataset(token_server.address, token="wrong", count=2, prefetch=0, retry_timeout=5)
    with pytest.raises(mpiflow.MpiFlowError):
        list(bad)


# -- TLS ----------------------------------------------------------------------------------------


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def _ca(d: Path, name: str) -> None:
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
             "-keyout", f"{name}.key", "-out", f"{name}.crt", "-days", "2", "-subj", f"/CN=mpiflow test {name}",
             "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign",
             cwd=d)


def _leaf(d: Path, ca: str, name: str, usage: str) -> None:
    _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
             "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={name}", cwd=d)
    (d / f"{name}.ext").write_text(
        f"subjectAltName=DNS:localhost,IP:127.0.0.1\nextendedKeyUsage={usage}\n"
        "basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature\n")
    _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.crt", "-CAkey", f"{ca}.key",
             "-CAcreateserial", "-out", f"{name}.crt", "-days", "2", "-extfile", f"{name}.ext", cwd=d)


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("no openssl command to make test certificates")
    d = tmp_path_factory.mktemp("pki")
    _ca(d, "ca")
    _ca(d, "other")
    _leaf(d, "ca", "server", "serverAuth")
    _leaf(d, "ca", "client", "clientAuth")
    return d


@pytest.fixture(scope="module")
def tls_server(binary, pki, token_file):
    tls = dict(tls_ca=str(pki / "ca.crt"), tls_cert=str(pki / "client.crt"), tls_key=str(pki / "client.key"))
    s = Server("real", client_kw=tls, extra=[
        "--size", "64x48", "--workers", "2", "--auth-token-file", str(token_file),
        "--tls-cert", str(pki / "server.crt"), "--tls-key", str(pki / "server.key"),
        "--tls-client-ca", str(pki / "ca.crt"),
    ]).start()
    yield s
    s.stop()


def test_tls_with_the_right_ca_and_a_client_certificate(tls_server, pki):
    kw = dict(tls_ca=str(pki / "ca.crt"), tls_cert=str(pki / "client.crt"), tls_key=str(pki / "client.key"))
    with mpiflow.Client(tls_server.address, token=TOKEN, timeout=30, **kw) as c:
        assert [s.index for s in c.stream(count=2)] == [0, 1]
    # PEM bytes work as well as paths; and the dataset passes them on
    as_bytes = {k: Path(v).read_bytes() for k, v in kw.items()}
    ds = mpiflow.MPIFlowDataset(tls_server.address, token=TOKEN, count=2, prefetch=0, **as_bytes)
    assert [s["index"] for s in ds] == [0, 1]
    # by name (the certificate carries localhost): tls_domain
    with mpiflow.Client(tls_server.address, token=TOKEN, timeout=30, tls_domain="localhost", **kw) as c:
        assert c.info().datasets


@pytest.mark.parametrize("how", ["other CA", "plaintext", "no client certificate"])
def test_tls_refuses(tls_server, pki, how):
    kw = {
        "other CA": dict(tls_ca=str(pki / "other.crt"), tls_cert=str(pki / "client.crt"),
                         tls_key=str(pki / "client.key")),
        "plaintext": {},
        "no client certificate": dict(tls_ca=str(pki / "ca.crt")),
    }[how]
    with mpiflow.Client(tls_server.address, token=TOKEN, timeout=3, wait=False, **kw) as c:
        assert c.health(tls_server.address) == "UNREACHABLE"
        with pytest.raises(mpiflow.NotReadyError):
            c.wait_ready(2)
