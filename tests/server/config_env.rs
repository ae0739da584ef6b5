//! Every key of the service's configuration round-trips through its `MPIFLOW_*` variable: for
//! each key of `ServiceConfig` and of its `[models]` and `[sample]` sections, `MPIFLOW_` and the
//! key in capitals set to a value other than the default gives a configuration whose value at
//! that key (and only there) differs from the default's. The keys come from the configuration
//! itself: every leaf of the default configuration serialised (a flattened section's keys
//! included) and every field serde's `Deserialize` names (the optional keys, absent from the
//! serialised default). The variables are passed to the loader as a list, never set in the
//! process's environment, so the tests do not race each other.

use mpiflow::sample::motion::MotionPreset;
use mpiflow::service::config::{ModelConfig, ServiceConfig};
use mpiflow::service::layers::field_names;
use toml::{Table, Value};

/// The sections of the configuration (keys whose value is a table).
const SECTIONS: [&str; 2] = ["models", "sample"];

fn default_table() -> Table {
    Table::try_from(ServiceConfig::default()).unwrap()
}

/// Every key path of the configuration that one variable sets (lists, such as `[[datasets]]`,
/// are not single variables).
fn keys() -> Vec<Vec<String>> {
    let mut out: Vec<Vec<String>> = Vec::new();
    let mut push = |p: Vec<String>| {
        if !out.contains(&p) {
            out.push(p);
        }
    };
    let table = default_table();
    for (k, v) in &table {
        match v {
            Value::Table(section) => {
                for (sub, v) in section {
                    if !matches!(v, Value::Table(_) | Value::Array(_)) {
                        push(vec![k.clone(), sub.clone()]);
                    }
                }
            }
            Value::Array(_) => {}
            _ => push(vec![k.clone()]),
        }
    }
    let sections =
        [("models", field_names::<ModelConfig>()), ("sample", field_names::<mpiflow::sample::config::SampleConfig>())];
    for &k in field_names::<ServiceConfig>() {
        if let Some((_, subs)) = sections.iter().find(|(s, _)| *s == k) {
            for &sub in *subs {
                let nested = table.get(k).and_then(|s| s.get(sub));
                if !matches!(nested, Some(Value::Table(_) | Value::Array(_))) {
                    push(vec![k.to_string(), sub.to_string()]);
                }
            }
        } else if !matches!(table.get(k), Some(Value::Array(_) | Value::Table(_))) {
            push(vec![k.to_string()]);
        }
    }
    out
}

fn at<'a>(t: &'a Table, path: &[String]) -> Option<&'a Value> {
    let (last, sections) = path.split_last()?;
    let mut t = t;
    for s in sections {
        t = t.get(s)?.as_table()?;
    }
    t.get(last)
}

/// The configuration with `MPIFLOW_{NAME}` = `value` over the defaults.
fn load(name: &str, value: &str) -> Result<ServiceConfig, String> {
    let mut c = ServiceConfig::default();
    c.apply_env_vars([(format!("MPIFLOW_{name}"), value.to_string())])?;
    Ok(c)
}

/// Values to try for a key whose default is `default`: one of another kind than the default's
/// value, first.
fn candidates(default: Option<&Value>) -> Vec<String> {
    match default {
        Some(Value::Boolean(b)) => vec![(!b).to_string()],
        Some(Value::Integer(n)) => vec![if *n > 0 { n - 1 } else { 1 }.to_string()],
        Some(Value::Float(f)) => vec![format!("{:?}", f + 1.5)],
        Some(Value::String(_)) => vec!["not-a-variant-name".into()],
        // an optional key unset by default: whichever of these its type takes
        _ => ["1", "true", "0.5", "a-value", "127.0.0.1:9"].map(String::from).to_vec(),
    }
}

/// The variants a key's error lists (`unknown variant `x`, expected one of `a`, `b``).
fn variants_in(error: &str) -> Vec<String> {
    let Some(i) = error.find("expected") else { return Vec::new() };
    error[i..].split('`').skip(1).step_by(2).map(str::to_string).collect()
}

#[test]
fn every_key_round_trips_through_its_variable() {
    let default = default_table();
    let keys = keys();
    assert!(keys.len() > 40, "found only {} keys", keys.len());
    let mut failures = Vec::new();
    for path in &keys {
        let name = path.last().unwrap().to_ascii_uppercase();
        let was = at(&default, path);
        let mut tried = Vec::new();
        let mut changed = None;
        let mut queue: std::collections::VecDeque<String> = candidates(was).into();
        while let Some(value) = queue.pop_front() {
            if tried.contains(&value) {
                continue;
            }
            tried.push(value.clone());
            match load(&name, &value) {
                Ok(c) => {
                    let got = Table::try_from(&c).unwrap();
                    if at(&got, path) != was {
                        changed = Some((value, got));
                        break;
                    }
                }
                Err(e) => {
                    // an enumeration: take a variant other than the default's; an untagged one
                    // (`[sample] motion`: a preset name or a ranges table) names none in its
                    // error, so the preset names are tried
                    let default_name = was.and_then(Value::as_str).unwrap_or_default();
                    let mut variants = variants_in(&e);
                    if variants.is_empty() {
                        variants = MotionPreset::ALL.iter().map(|p| p.name().to_string()).collect();
                    }
                    queue.extend(variants.into_iter().filter(|v| v != default_name));
                }
            }
        }
        let Some((value, got)) = changed else {
            failures
                .push(format!("MPIFLOW_{name} (key {}): no value changed the key (tried {tried:?})", path.join(".")));
            continue;
        };
        // only that key changed
        for other in &keys {
            if other != path && at(&got, other) != at(&default, other) {
                failures.push(format!("MPIFLOW_{name}={value} changed {} too", other.join(".")));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn the_sources_variable_replaces_the_datasets() {
    let c = load("SOURCES", "a=/data/a,/data/b").unwrap();
    assert_eq!(c.datasets.len(), 2, "{:?}", c.datasets);
    assert_ne!(c.datasets, ServiceConfig::default().datasets);
}

#[test]
fn the_key_list_holds_every_section() {
    let keys = keys();
    for section in SECTIONS {
        assert!(keys.iter().any(|k| k.len() == 2 && k[0] == section), "no key of [{section}]");
        assert!(!keys.iter().any(|k| k.len() == 1 && k[0] == section), "[{section}] as one key");
    }
    assert!(keys.iter().any(|k| k == &["metrics_addr"]), "an optional key unset by default is listed");
}
