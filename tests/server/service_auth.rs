//! Security of the gRPC service on loopback: the bearer token (every `mpiflow.v1` call refused
//! with UNAUTHENTICATED without it or with a wrong one, no sample made; health open), TLS with a
//! server certificate (the right CA connects, another CA or plaintext does not) and client
//! certificates (required when `tls_client_ca` is set). Certificates are made here with rcgen.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use mpiflow::service::client::{channel, client_for, client_with_token, connect_with, BearerToken, ClientOptions};
use mpiflow::service::pb;
use mpiflow::service::{start, RunningServer, ServiceConfig};
use rcgen::{
    BasicConstraints, CertificateParams, CertifiedIssuer, DnType, ExtendedKeyUsagePurpose, IsCa, KeyPair,
    KeyUsagePurpose,
};
use tonic::transport::Endpoint;
use tonic::Code;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

const TOKEN: &str = "s3cret-Token_0123456789";

fn config() -> ServiceConfig {
    ServiceConfig {
        addr: "127.0.0.1:0".into(),
        size: Some("64x48".into()),
        workers: 2,
        log_level: "warn".into(),
        ..ServiceConfig::default()
    }
}

/// A CA, and certificates it signs, written as PEM files into a folder of their own.
struct Pki {
    dir: PathBuf,
}

impl Pki {
    fn new(name: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("mpiflow-auth-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        Pki { dir }
    }

    fn path(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }

    fn write(&self, name: &str, text: &str) -> PathBuf {
        let p = self.path(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    /// A self-signed CA: writes NAME.crt and returns the issuer.
    fn ca(&self, name: &str) -> CertifiedIssuer<'static, KeyPair> {
        let mut p = CertificateParams::new(Vec::<String>::new()).unwrap();
        p.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        p.distinguished_name.push(DnType::CommonName, format!("mpiflow test CA {name}"));
        p.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign, KeyUsagePurpose::DigitalSignature];
        let ca = CertifiedIssuer::self_signed(p, KeyPair::generate().unwrap()).unwrap();
        self.write(&format!("{name}.crt"), &ca.pem());
        ca
    }

    /// A certificate signed by `ca` for loopback: writes NAME.crt and NAME.key.
    fn leaf(&self, ca: &CertifiedIssuer<'static, KeyPair>, name: &str, usage: ExtendedKeyUsagePurpose) {
        let mut p = CertificateParams::new(vec!["localhost".to_string(), "127.0.0.1".to_string()]).unwrap();
        p.distinguished_name.push(DnType::CommonName, name);
        p.extended_key_usages = vec![usage];
        let key = KeyPair::generate().unwrap();
        let cert = p.signed_by(&key, ca).unwrap();
        self.write(&format!("{name}.crt"), &cert.pem());
        self.write(&format!("{name}.key"), &key.serialize_pem());
    }
}

impl Drop for Pki {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// CA `ca` signs `server` and `client`; CA `other` signs `stranger` (a client of another CA).
fn pki(name: &str) -> Pki {
    let pki = Pki::new(name);
    let ca = pki.ca("ca");
    pki.leaf(&ca, "server", ExtendedKeyUsagePurpose::ServerAuth);
    pki.leaf(&ca, "client", ExtendedKeyUsagePurpose::ClientAuth);
    let other = pki.ca("other");
    pki.leaf(&other, "stranger", ExtendedKeyUsagePurpose::ClientAuth);
    pki
}

fn tls_config(pki: &Pki) -> ServiceConfig {
    ServiceConfig { tls_cert: Some(pki.path("server.crt")), tls_key: Some(pki.path("server.key")), ..config() }
}

fn trusting(pki: &Pki, ca: &str) -> ClientOptions {
    ClientOptions { tls_ca: Some(pki.path(&format!("{ca}.crt"))), ..ClientOptions::default() }
}

fn with_cert(o: ClientOptions, pki: &Pki, name: &str) -> ClientOptions {
    ClientOptions {
        tls_cert: Some(pki.path(&format!("{name}.crt"))),
        tls_key: Some(pki.path(&format!("{name}.key"))),
        ..o
    }
}

/// Health without a token (the probes' way): waits for SERVING.
async fn wait_serving(addr: &str, o: &ClientOptions) {
    let ch = channel(addr, &ClientOptions { token: None, ..o.clone() }).await.expect("health connects");
    let mut h = HealthClient::new(ch);
    // the health Watch sends the status now and on every change: no polling
    let mut updates = h.watch(HealthCheckRequest { service: String::new() }).await.unwrap().into_inner();
    let serving = async {
        while let Some(u) = updates.message().await.expect("health watch") {
            if u.status == ServingStatus::Serving as i32 {
                return;
            }
        }
        panic!("the health watch ended before SERVING");
    };
    tokio::time::timeout(Duration::from_secs(30), serving).await.expect("never SERVING");
}

async fn serving(c: ServiceConfig, o: &ClientOptions) -> RunningServer {
    let s = start(c).await.expect("server starts");
    wait_serving(&s.addr.to_string(), o).await;
    s
}

fn req(count: u64) -> pb::StreamRequest {
    pb::StreamRequest { count, ..pb::SampleSpec { seed: 3, ..Default::default() }.stream() }
}

/// Connects with `o` and pulls `count` samples: their indices, or the first error.
async fn pull(addr: &str, o: &ClientOptions, count: u64) -> Result<Vec<u64>, String> {
    let mut c = connect_with(addr, o).await.map_err(|e| format!("connect: {e}"))?;
    let mut s =
        c.stream_samples(req(count)).await.map_err(|e| format!("{:?}: {}", e.code(), e.message()))?.into_inner();
    let mut got = vec![];
    while let Some(b) = s.message().await.map_err(|e| format!("{:?}: {}", e.code(), e.message()))? {
        got.extend(b.samples.iter().map(|s| s.index));
    }
    Ok(got)
}

/// A connection the server's TLS refused: the connect or the first call fails in the transport
/// (a transport error, CANCELLED, UNAVAILABLE, or an HTTP/2 protocol error when a plaintext
/// client reads the TLS alert, depending on when the server closes the connection).
fn assert_transport_failure(e: &str) {
    let transport = ["transport error", "Cancelled", "Unavailable", "h2 protocol error"];
    assert!(transport.iter().any(|t| e.contains(t)), "{e}");
}

fn unauthenticated<T: std::fmt::Debug>(r: Result<T, tonic::Status>, what: &str, says: &str) {
    let e = r.expect_err(what);
    assert_eq!(e.code(), Code::Unauthenticated, "{what}: {e:?}");
    assert!(e.message().contains(says), "{what}: {}", e.message());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_token_guards_every_call_but_health() {
    let s = serving(ServiceConfig { auth_token: Some(TOKEN.into()), ..config() }, &ClientOptions::default()).await;
    let addr = s.addr.to_string();
    let made = s.state.metrics.samples_generated.get();
    assert_eq!(made, 1, "the warm-up sample");
    let ch = Endpoint::from_shared(format!("http://{addr}")).unwrap().connect().await.unwrap();
    let chunk = pb::SourceChunk { dataset: "up".into(), name: "a".into(), kind: "image".into(), data: vec![1; 64] };

    // no token
    let mut c = client_for(ch.clone());
    let says = "missing bearer token";
    unauthenticated(c.stream_samples(req(2)).await, "StreamSamples", says);
    unauthenticated(c.get_sample(pb::SampleRequest::default()).await, "GetSample", says);
    unauthenticated(c.get_info(pb::InfoRequest {}).await, "GetInfo", says);
    unauthenticated(c.upload_sources(tokio_stream::iter(vec![chunk.clone()])).await, "UploadSources", says);

    // a wrong token, a prefix of the right one, another scheme
    for (token, says) in [("wrong", "invalid bearer token"), (&TOKEN[..10], "invalid bearer token")] {
        let mut c = client_with_token(ch.clone(), BearerToken::new(Some(token)).unwrap());
        unauthenticated(c.stream_samples(req(2)).await, "StreamSamples", says);
        unauthenticated(c.get_sample(pb::SampleRequest::default()).await, "GetSample", says);
        unauthenticated(c.get_info(pb::InfoRequest {}).await, "GetInfo", says);
        unauthenticated(c.upload_sources(tokio_stream::iter(vec![chunk.clone()])).await, "UploadSources", says);
    }
    let mut basic = client_for(ch.clone());
    let mut r = tonic::Request::new(pb::InfoRequest {});
    r.metadata_mut().insert("authorization", format!("Basic {TOKEN}").parse().unwrap());
    unauthenticated(basic.get_info(r).await, "GetInfo with Basic", "malformed authorization header");

    // reflection is guarded too
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::ServerReflectionRequest;
    let list = || ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let r = ServerReflectionClient::new(ch.clone()).server_reflection_info(tokio_stream::iter(vec![list()])).await;
    unauthenticated(r, "reflection", "missing bearer token");
    let mut refl = ServerReflectionClient::with_interceptor(ch.clone(), BearerToken::new(Some(TOKEN)).unwrap());
    let mut answers = refl.server_reflection_info(tokio_stream::iter(vec![list()])).await.unwrap().into_inner();
    assert!(answers.message().await.unwrap().is_some(), "reflection answers with the token");

    // nothing was made or stored for the refused calls: the token check runs before any handler,
    // so a refused call registers no stream with the pool and dispatches no job (the warm-up's
    // stream closed before health said SERVING, and its sample was counted before it was
    // delivered): with no stream open nothing can still be on its way, and the count is final
    let pool = s.state.scheduler.stats();
    assert_eq!((pool.streams, pool.waiting_scene), (0, 0), "a refused call reached the pool");
    assert_eq!(s.state.metrics.samples_generated.get(), made, "a refused call made a sample");
    assert_eq!(s.state.active_streams(), 0);
    let metrics = s.state.metrics.render();
    let refused = metrics.lines().find(|l| l.contains("code=\"Unauthenticated\"")).unwrap_or_default();
    assert!(refused.ends_with(" 14"), "5 calls without a token, 8 with wrong ones, 1 malformed: {refused:?}");

    // the right token
    let token = ClientOptions { token: Some(TOKEN.into()), ..ClientOptions::default() };
    assert_eq!(pull(&addr, &token, 3).await.unwrap(), [0, 1, 2]);
    let mut c = connect_with(&addr, &token).await.unwrap();
    let info = c.get_info(pb::InfoRequest {}).await.unwrap().into_inner();
    assert!(info.datasets.iter().all(|d| d.name != "up"), "the refused upload made a dataset");
    assert_eq!(c.get_sample(pb::SampleRequest { index: 4, ..Default::default() }).await.unwrap().into_inner().index, 4);
    // health answers without a token (also for the named service)
    let st = HealthClient::new(ch)
        .check(HealthCheckRequest { service: "mpiflow.v1.MpiFlow".into() })
        .await
        .unwrap()
        .into_inner()
        .status;
    assert_eq!(st, ServingStatus::Serving as i32);
    s.shutdown(Duration::from_secs(2)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_connects_only_with_the_right_ca() {
    let pki = pki("tls");
    let right = trusting(&pki, "ca");
    let c = ServiceConfig { health_addr: Some("127.0.0.1:0".into()), ..tls_config(&pki) };
    let s = serving(c, &right).await;
    let addr = s.addr.to_string();
    assert_eq!(pull(&addr, &right, 3).await.unwrap(), [0, 1, 2]);
    // the plaintext health-only listener (for the kubelet's probes) answers health and nothing else
    let plain = s.health_addr.unwrap().to_string();
    wait_serving(&plain, &ClientOptions::default()).await;
    let ch = channel(&plain, &ClientOptions::default()).await.unwrap();
    let e = client_for(ch).get_info(pb::InfoRequest {}).await.unwrap_err();
    assert_eq!(e.code(), Code::Unimplemented, "{e:?}");
    // the same by name (the certificate is for localhost and 127.0.0.1) and with an https:// address
    let port = s.addr.port();
    assert_eq!(pull(&format!("https://localhost:{port}"), &right, 1).await.unwrap(), [0]);
    let named = ClientOptions { tls_domain: Some("localhost".into()), ..right.clone() };
    assert_eq!(pull(&addr, &named, 1).await.unwrap(), [0]);
    // a name the certificate does not carry
    let misnamed = ClientOptions { tls_domain: Some("elsewhere.example".into()), ..right.clone() };
    let e = pull(&addr, &misnamed, 1).await.unwrap_err();
    assert!(e.starts_with("connect:"), "{e}");

    // a client trusting another CA does not connect
    let e = pull(&addr, &trusting(&pki, "other"), 1).await.unwrap_err();
    assert!(e.starts_with("connect:") && e.to_lowercase().contains("certificate"), "{e}");
    // neither does a plaintext client
    let e = pull(&addr, &ClientOptions::default(), 1).await.unwrap_err();
    assert_transport_failure(&e);
    assert_eq!(s.state.active_streams(), 0);
    s.shutdown(Duration::from_secs(2)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn client_certificates_are_required_with_a_client_ca() {
    let pki = pki("mtls");
    let c = ServiceConfig { tls_client_ca: Some(pki.path("ca.crt")), ..tls_config(&pki) };
    let with = with_cert(trusting(&pki, "ca"), &pki, "client");
    let s = serving(c, &with).await;
    let addr = s.addr.to_string();
    assert_eq!(pull(&addr, &with, 2).await.unwrap(), [0, 1]);
    // without a client certificate, or with one of another CA: no samples
    // (with TLS 1.3 the server refuses after the client's handshake: the first call fails)
    let e = pull(&addr, &trusting(&pki, "ca"), 1).await.unwrap_err();
    assert_transport_failure(&e);
    let e = pull(&addr, &with_cert(trusting(&pki, "ca"), &pki, "stranger"), 1).await.unwrap_err();
    assert_transport_failure(&e);
    assert_eq!(s.state.metrics.samples_generated.get(), 3, "the warm-up and the two pulled");
    s.shutdown(Duration::from_secs(2)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_and_token_together_through_the_cli() {
    let pki = pki("cli");
    std::fs::write(pki.path("token"), format!("{TOKEN}\n")).unwrap();
    let c = ServiceConfig { auth_token_file: Some(pki.path("token")), ..tls_config(&pki) };
    let right = ClientOptions { token: Some(TOKEN.into()), ..trusting(&pki, "ca") };
    let s = serving(c, &right).await;
    let addr = s.addr.to_string();
    let ca = path(&pki.path("ca.crt")).to_string();
    let token_file = path(&pki.path("token")).to_string();
    let pull = |extra: &[&str]| {
        let mut args: Vec<String> = ["pull", "--addr", &addr, "--count", "2", "--tls-ca", &ca].map(String::from).into();
        args.extend(extra.iter().map(std::string::ToString::to_string));
        tokio::task::spawn_blocking(move || run(args))
    };
    let (ok, out) = pull(&["--token", TOKEN]).await.unwrap();
    assert!(ok && out.contains("2 samples"), "pull with the token: {out}");
    let (ok, out) = pull(&["--token-file", &token_file]).await.unwrap();
    assert!(ok && out.contains("2 samples"), "pull with --token-file: {out}");
    let (ok, out) = pull(&[]).await.unwrap();
    assert!(!ok && out.contains("Unauthenticated") && out.contains("missing bearer token"), "{out}");
    let (ok, out) = pull(&["--token", "nope"]).await.unwrap();
    assert!(!ok && out.contains("invalid bearer token"), "{out}");
    // health: TLS, no token
    let h = ["health", "--addr", &addr, "--tls-ca", &ca].map(String::from).into();
    let (ok, out) = tokio::task::spawn_blocking(move || run(h)).await.unwrap();
    assert!(ok && out.contains("SERVING"), "{out}");
    s.shutdown(Duration::from_secs(2)).await;
}

fn path(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Runs the binary: (success, stdout + stderr).
fn run(args: Vec<String>) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_mpiflow")).args(&args).output().expect("mpiflow runs");
    (out.status.success(), String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_security_settings_fail_the_start_up() {
    let pki = pki("bad");
    let missing = ServiceConfig { tls_key: Some(pki.path("nope.key")), ..tls_config(&pki) };
    let e = start(missing).await.unwrap_err().to_string();
    assert!(e.contains("tls_key") && e.contains("nope.key"), "{e}");
    let half = ServiceConfig { tls_key: None, ..tls_config(&pki) };
    assert!(start(half).await.unwrap_err().to_string().contains("tls_cert and tls_key"));
    let both = ServiceConfig { auth_token: Some("a".into()), auth_token_file: Some(pki.path("t")), ..config() };
    assert!(start(both).await.unwrap_err().to_string().contains("auth_token"));
    let spaced = ServiceConfig { auth_token: Some("two words".into()), ..config() };
    assert!(start(spaced).await.unwrap_err().to_string().contains("auth_token"));
}

/// `mpiflow serve` with `auth_token_file` in its configuration file and one token setting of a
/// layer above it empty: an empty `MPIFLOW_AUTH_TOKEN` or `MPIFLOW_AUTH_TOKEN_FILE` (which would
/// otherwise replace the file's token file with nothing), an empty `--auth-token-file`, a token
/// file that is empty or `/dev/zero`. Each stops the start-up (exit status 2) with an error
/// naming the setting (one line for the configuration's own); none serves without the token.
#[test]
fn an_empty_token_setting_in_any_layer_stops_the_real_binary() {
    use std::io::BufRead;
    use std::process::Stdio;
    let pki = pki("empty");
    let token = pki.write("token", TOKEN);
    let blank = pki.write("blank", " \n");
    let with_file = |file: &Path| {
        pki.write(
            &format!("{}.toml", file.file_name().unwrap().to_str().unwrap()),
            &format!("addr = \"127.0.0.1:0\"\nsize = \"64x48\"\nworkers = 1\nauth_token_file = \"{}\"\n", path(file)),
        )
    };
    let good = with_file(&token);
    /// (configuration file, environment, flags, what the error says)
    type Case<'a> = (PathBuf, Vec<(&'a str, &'a str)>, Vec<&'a str>, &'a str);
    let cases: Vec<Case> = vec![
        (good.clone(), vec![("MPIFLOW_AUTH_TOKEN", "")], vec![], "MPIFLOW_AUTH_TOKEN is set but empty"),
        (good.clone(), vec![("MPIFLOW_AUTH_TOKEN_FILE", "")], vec![], "MPIFLOW_AUTH_TOKEN_FILE is set but empty"),
        (good.clone(), vec![("MPIFLOW_AUTH_TOKEN", "  ")], vec![], "MPIFLOW_AUTH_TOKEN is set but empty"),
        // clap itself refuses an empty value of a path flag
        (good, vec![], vec!["--auth-token-file", ""], "a value is required for '--auth-token-file"),
        (with_file(&blank), vec![], vec![], "holds no token"),
        (with_file(Path::new("/dev/zero")), vec![], vec![], "larger than"),
    ];
    for (config, env, flags, says) in cases {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_mpiflow"));
        cmd.args(["serve", "--log-level", "warn", "--config", path(&config)]).args(&flags);
        cmd.env_remove("MPIFLOW_AUTH_TOKEN").env_remove("MPIFLOW_AUTH_TOKEN_FILE");
        for (k, v) in &env {
            cmd.env(k, v);
        }
        let mut child = cmd.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
        let mut line = String::new();
        std::io::BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
        if !line.is_empty() {
            child.kill().unwrap();
            child.wait().unwrap();
            panic!("{env:?} {flags:?}: the server started: {line}");
        }
        let out = child.wait_with_output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{env:?} {flags:?}: {err}");
        assert!(err.starts_with("error: ") && err.contains(says), "{env:?} {flags:?}: {err}");
        assert!(!flags.is_empty() || err.lines().count() == 1, "{env:?}: one line: {err}");
    }
}
