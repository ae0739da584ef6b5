//! The unit tests of the soak: the verdict, the CPU time, the metric values.

use super::process::stat_cpu_s;
use super::*;

#[test]
fn a_kind_of_client_that_got_nothing_done_fails_the_soak() {
    let mut r = SoakReport { fast_samples: 10, ..SoakReport::default() };
    assert!(r.passed());
    r.idle_kinds.push("slow");
    assert!(!r.passed());
    assert!(r.summary().iter().any(|l| l == "clients that got nothing done: slow"), "{:?}", r.summary());
    assert_eq!(r.summary().last().map(String::as_str), Some("soak: FAIL"));
}

#[test]
fn cpu_time_is_user_plus_system_after_a_command_name_with_spaces_and_parentheses() {
    // pid (comm) state ppid pgrp session tty tpgid flags minflt cminflt majflt cmajflt utime stime ...
    let line = "4242 (mpi (flow) x) S 1 4242 4242 0 -1 4194560 100 0 0 0 250 75 0 0 20 0 3 0";
    assert_eq!(stat_cpu_s(line), Some(3.25));
    assert_eq!(stat_cpu_s("4242 (truncated) S 1 2"), None);
    let me = cpu_s(std::process::id()).expect("this process's /proc/PID/stat");
    assert!(me >= 0.0 && me.is_finite());
}

#[test]
fn metric_values_are_summed_over_labels_and_absent_ones_are_none() {
    let text = "# HELP mpiflow_buffered_bytes x\n# TYPE mpiflow_buffered_bytes gauge\n\
                mpiflow_buffered_bytes 1024\nmpiflow_buffered_bytes_limit 5\n\
                mpiflow_streams{dataset=\"a\"} 2\nmpiflow_streams{dataset=\"b\"} 3\n";
    assert_eq!(metric_value(text, "mpiflow_buffered_bytes"), Some(1024.0));
    assert_eq!(metric_value(text, "mpiflow_streams"), Some(5.0));
    assert_eq!(metric_value(text, "mpiflow_missing"), None);
}
