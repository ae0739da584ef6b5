//! The soak test, short: a real `mpiflow serve` (child process, free loopback port) under fast,
//! stalled, slow, cancelling, uploading, unary, unread, idle and batch-stalled clients for 20 s
//! at 160x120; what the soak reports
//! must show no lost or repeated index for the fast clients, no unexpected error code, every
//! kind of client at work, and the server's memory read from its /proc status.

use std::time::Duration;

use mpiflow::bench::soak::{run_soak, SoakConfig};

#[test]
fn a_short_soak_loses_and_repeats_no_index_and_sees_no_unexpected_error() {
    // idle connections are closed after 2 s, so that the idle clients see it within the run
    let dir = std::env::temp_dir().join(format!("mpiflow-soak-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let config = dir.join("serve.toml");
    std::fs::write(&config, "idle_connection_timeout_s = 2.0\n").unwrap();
    let cfg = SoakConfig {
        exe: env!("CARGO_BIN_EXE_mpiflow").into(),
        duration: Duration::from_secs(20),
        solo: Duration::from_secs(4),
        size: "160x120".into(),
        workers: 2,
        fast: 2,
        stalled: 3,
        slow: 1,
        cancelling: 1,
        uploading: 1,
        unary: 4,
        unread: 1,
        idle: 2,
        batch_stall: 1,
        watch: 2,
        window_streams: 3,
        unread_calls: 8,
        hostile_frames: 2,
        attacker_addresses: 4,
        report_every: Duration::from_secs(5),
        server_args: vec!["--config".into(), config.display().to_string()],
    };
    let mut lines = Vec::new();
    let report = run_soak(&cfg, &mut |l: &str| lines.push(l.to_string())).expect("the soak runs");
    let text = [lines, report.summary()].concat().join("\n");
    eprintln!("{text}");
    assert_eq!((report.lost, report.repeated), (0, 0), "{text}");
    assert_eq!(report.unexpected, 0, "{text}");
    assert!(report.passed(), "{text}");
    assert!(report.solo_per_s > 0.0 && report.fast_samples > 0, "{text}");
    // every kind of client did its part
    assert!(report.stalled_streams >= 3 && report.slow_samples > 0, "{text}");
    assert!(report.cancelled_streams > 0 && report.uploads > 0, "{text}");
    assert!(report.unary_samples > 0 && report.unread_calls > 0 && report.idle_closed > 0, "{text}");
    assert!(report.watches > 0 && report.window_streams > 0, "{text}");
    // the byte budget held, whatever the hostile clients' addresses
    assert!(report.budget_bytes > 0.0 && report.max_buffered_bytes <= report.budget_bytes, "{text}");
    // a newcomer was never turned away
    assert_eq!(report.newcomers_refused, 0, "{text}");
    // the server's memory was read over time
    assert!(!report.points.is_empty() && report.points.iter().all(|p| p.rss_mib > 0.0), "{text}");
    assert!(report.idle_rss_mib > 0.0 && report.peak_rss_mib >= report.idle_rss_mib, "{text}");
}
