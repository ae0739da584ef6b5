//! Command-line misuse through the real `mpiflow` binary: every command prints clap's whole
//! message (the problem, the usage line, a suggestion for a near miss, the pointer to --help) on
//! stderr, nothing on stdout, with exit status 2.

use std::process::Command;

const BIN: &str = env!("CARGO_BIN_EXE_mpiflow");

/// (arguments, what clap's message says, the usage line it shows where clap shows one: not
/// for a value its parser refuses)
const MISUSES: [(&[&str], &[&str], Option<&str>); 12] = [
    // a near miss of a command: clap's suggestion
    (&["pul"], &["unrecognized subcommand 'pul'", "tip: a similar subcommand exists: 'pull'"], Some("Usage: mpiflow")),
    (&["serv"], &["tip: a similar subcommand exists: 'serve'"], Some("Usage: mpiflow")),
    // a required argument left out: its name on the next line
    (
        &["pull", "--addr", "127.0.0.1:1"],
        &["the following required arguments were not provided:", "--count <N>"],
        Some("Usage: mpiflow pull"),
    ),
    (
        &["generate"],
        &["the following required arguments were not provided:", "--count <N>", "--out <DIR>"],
        Some("Usage: mpiflow generate"),
    ),
    (&["bake", "--out", "x"], &["--source <DIR|SHARDS>"], Some("Usage: mpiflow bake")),
    // an unknown flag, a near miss of a real one
    (&["serve", "--port", "5"], &["unexpected argument '--port' found"], Some("Usage: mpiflow serve")),
    (
        &["generate", "--count", "1", "--out", "x", "--sise", "64x48"],
        &["tip: a similar argument exists: '--size'"],
        Some("Usage: mpiflow generate"),
    ),
    (
        &["pull", "--count", "1", "--adr", "127.0.0.1:1"],
        &["tip: a similar argument exists: '--addr'"],
        Some("Usage: mpiflow pull"),
    ),
    // values out of range or not parsed
    (&["pull", "--count", "0"], &["invalid value '0' for '--count <N>'"], None),
    (&["generate", "--count", "1", "--out", "x", "--size", "8x8"], &["invalid value '8x8' for '--size <WxH>'"], None),
    (
        &["bake", "--source", "s", "--out", "o", "--format", "zip"],
        &["invalid value 'zip' for '--format <FORMAT>'", "[possible values: reference, webdataset]"],
        None,
    ),
    // a flag without its value
    (&["health", "--addr"], &["a value is required for '--addr <HOST:PORT>' but none was supplied"], None),
];

#[test]
fn every_misuse_prints_claps_whole_message_with_exit_status_2() {
    for (args, says, usage) in MISUSES {
        let out = Command::new(BIN).args(args).output().unwrap();
        let stderr = String::from_utf8(out.stderr).unwrap();
        assert_eq!(out.status.code(), Some(2), "{args:?}: {stderr}");
        assert!(out.stdout.is_empty(), "{args:?}: stdout {:?}", String::from_utf8_lossy(&out.stdout));
        assert!(stderr.starts_with("error: "), "{args:?}: {stderr}");
        for s in says {
            assert!(stderr.contains(s), "{args:?}: no {s:?} in {stderr}");
        }
        if let Some(usage) = usage {
            assert!(stderr.contains(usage), "{args:?}: no {usage:?} in {stderr}");
        }
        // more than the first line: the usage or the pointer to --help follow it
        assert!(stderr.lines().count() >= 3, "{args:?}: {stderr}");
        assert!(stderr.contains("For more information, try '--help'."), "{args:?}: {stderr}");
    }
}

#[test]
fn help_and_version_are_not_errors() {
    for args in [&["--help"][..], &["--version"], &["serve", "--help"]] {
        let out = Command::new(BIN).args(args).output().unwrap();
        assert_eq!(out.status.code(), Some(0), "{args:?}");
        assert!(!out.stdout.is_empty() && out.stderr.is_empty(), "{args:?}");
    }
}
