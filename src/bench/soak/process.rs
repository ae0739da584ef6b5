//! The server under test: a `mpiflow serve` child process, and what is read from it (its memory
//! and CPU time from `/proc`, its metrics over HTTP).

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};

use super::report::SoakError;

/// The resident memory (`VmRSS`) of a process in MiB.
pub fn rss_mib(pid: u32) -> Option<f64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = s.lines().find(|l| l.starts_with("VmRSS:"))?;
    Some(line.split_whitespace().nth(1)?.parse::<f64>().ok()? / 1024.0)
}

/// CPU seconds (user + system, all threads) process `pid` has used so far, from
/// `/proc/PID/stat` (Linux; its unit, `USER_HZ`, is 100 per second in the kernel's ABI). None
/// where there is no `/proc`.
pub fn cpu_s(pid: u32) -> Option<f64> {
    stat_cpu_s(&std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?)
}

/// [`cpu_s`] of one `/proc/PID/stat` line.
pub(super) fn stat_cpu_s(s: &str) -> Option<f64> {
    // the fields after the command name, which is in parentheses and may hold spaces
    let rest = &s[s.rfind(')')? + 1..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the line, 12 and 13 after the name
    let ticks = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// A `mpiflow serve` child process on loopback; SIGTERM and wait on drop.
pub struct ServerProcess {
    child: Child,
    /// `HOST:PORT` of the gRPC listener.
    pub addr: String,
    /// `HOST:PORT` of `/metrics`, when the server printed one.
    pub metrics_addr: Option<String>,
}

impl ServerProcess {
    /// Starts `exe serve ARGS` and reads the addresses it prints (`mpiflow serving on ...`, then
    /// `mpiflow metrics on http://.../metrics` when `--metrics-addr` is among the arguments).
    pub fn start(exe: &std::path::Path, args: &[String]) -> Result<Self, SoakError> {
        let mut child = Command::new(exe)
            .arg("serve")
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .map_err(|e| SoakError(format!("cannot start {} serve: {e}", exe.display())))?;
        let stdout = child.stdout.take().ok_or_else(|| SoakError("no stdout from mpiflow serve".into()))?;
        let mut lines = BufReader::new(stdout).lines();
        let mut next = || lines.next().and_then(Result::ok).unwrap_or_default();
        let first = next();
        let Some(addr) = first.trim().strip_prefix("mpiflow serving on ").map(str::to_string) else {
            let _ = child.kill();
            let _ = child.wait();
            return Err(SoakError(format!("mpiflow serve printed {:?}", crate::failure::printable(&first, 200))));
        };
        let metrics_addr = if args.iter().any(|a| a == "--metrics-addr") {
            let m = next();
            m.trim()
                .strip_prefix("mpiflow metrics on http://")
                .and_then(|m| m.strip_suffix("/metrics"))
                .map(str::to_string)
        } else {
            None
        };
        // keep reading the server's stdout to its end: a closed pipe would fail its later writes
        std::thread::spawn(move || lines.for_each(drop));
        Ok(Self { child, addr, metrics_addr })
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// SIGTERM (a graceful drain), then waits up to `grace`; the exit status (`None` when it had
    /// to be killed).
    pub fn terminate(mut self, grace: Duration) -> Option<std::process::ExitStatus> {
        let _ = Command::new("kill").arg("-TERM").arg(self.child.id().to_string()).status();
        let end = Instant::now() + grace;
        while Instant::now() < end {
            match self.child.try_wait() {
                Ok(Some(status)) => return Some(status),
                Ok(None) => std::thread::sleep(Duration::from_millis(50)),
                Err(_) => break,
            }
        }
        None // Drop kills it
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// The sum of a metric's samples in a Prometheus text exposition (`None` when absent).
pub fn metric_value(text: &str, name: &str) -> Option<f64> {
    let mut found = None;
    for line in text.lines().filter(|l| !l.starts_with('#')) {
        let Some(rest) = line.strip_prefix(name) else { continue };
        if !(rest.starts_with(' ') || rest.starts_with('{')) {
            continue;
        }
        if let Some(v) = rest.rsplit(' ').next().and_then(|v| v.parse::<f64>().ok()) {
            *found.get_or_insert(0.0) += v;
        }
    }
    found
}

/// `GET /metrics` over plain HTTP/1.0.
pub async fn scrape(addr: &str) -> Option<String> {
    let mut s = tokio::net::TcpStream::connect(addr).await.ok()?;
    s.write_all(format!("GET /metrics HTTP/1.0\r\nHost: {addr}\r\n\r\n").as_bytes()).await.ok()?;
    let mut body = Vec::new();
    s.read_to_end(&mut body).await.ok()?;
    Some(String::from_utf8_lossy(&body).into_owned())
}
