//! The configuration's layers: defaults < TOML file < `MPIFLOW_*` environment < flags. Each layer
//! is a TOML table merged key by key over the ones below it and read back into
//! [`ServiceConfig`] by serde, so a key is declared once, as a field of `ServiceConfig` (or of its
//! `[models]` and `[sample]` sections): its environment name is derived from it (`MPIFLOW_` and
//! the key in capitals: `max_streams` is `MPIFLOW_MAX_STREAMS`, `[sample] max_objects` is
//! `MPIFLOW_MAX_OBJECTS`), and a flag names the key it sets by its serde name.
//!
//! Hand-written, and why: two short names kept for the deployments that use them
//! (`MPIFLOW_PREFETCH` = `default_prefetch`, `MPIFLOW_PRESET` = `[sample] motion`);
//! `MPIFLOW_SOURCES` (a list of `NAME=PATH` in one variable, for `[[datasets]]`); the rule that
//! a layer giving `auth_token` or `auth_token_file` replaces both below it (a token from the
//! environment replaces the file's token file); and the security keys ([`NEVER_EMPTY`]), which an
//! empty variable does not unset: it is refused.

use serde::de::{self, Deserialize, Deserializer, Visitor};
use serde::Serialize;
use toml::{Table, Value};

use super::config::{DatasetConfig, ModelConfig, ServiceConfig};
use crate::sample::config::SampleConfig;

/// The prefix of the configuration's environment variables.
pub const ENV_PREFIX: &str = "MPIFLOW_";

/// Short environment names kept beside the derived ones: (name without the prefix, key path).
const ENV_ALIASES: [(&str, &[&str]); 2] = [("PREFETCH", &["default_prefetch"]), ("PRESET", &["sample", "motion"])];

/// The environment variable (without the prefix) that replaces `[[datasets]]`.
const ENV_SOURCES: &str = "SOURCES";

/// Keys of which a layer gives at most one: giving either replaces both below it.
const ONE_OF: [&str; 2] = ["auth_token", "auth_token_file"];

/// The security keys: an empty variable is refused instead of unsetting them, so that a setting
/// lost on the way (an empty secret, a template that rendered nothing) stops the start-up rather
/// than turning the token or TLS off.
pub const NEVER_EMPTY: [&str; 5] = ["auth_token", "auth_token_file", "tls_cert", "tls_key", "tls_client_ca"];

/// The field names serde gives a struct's `Deserialize` (what `deny_unknown_fields` accepts).
pub fn field_names<'de, T: Deserialize<'de>>() -> &'static [&'static str] {
    struct Probe<'a>(&'a mut &'static [&'static str]);
    impl<'de> Deserializer<'de> for Probe<'_> {
        type Error = de::value::Error;
        fn deserialize_any<V: Visitor<'de>>(self, _: V) -> Result<V::Value, Self::Error> {
            Err(de::Error::custom("not a struct"))
        }
        fn deserialize_struct<V: Visitor<'de>>(
            self,
            _: &'static str,
            fields: &'static [&'static str],
            _: V,
        ) -> Result<V::Value, Self::Error> {
            *self.0 = fields;
            Err(de::Error::custom("field names read"))
        }
        serde::forward_to_deserialize_any! {
            bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string bytes byte_buf
            option unit unit_struct newtype_struct seq tuple tuple_struct map enum identifier
            ignored_any
        }
    }
    let mut fields: &'static [&'static str] = &[];
    let _ = T::deserialize(Probe(&mut fields));
    fields
}

/// The keys of a section of [`ServiceConfig`] (a key whose value is a table).
fn section_keys(section: &str) -> &'static [&'static str] {
    match section {
        "models" => field_names::<ModelConfig>(),
        "sample" => field_names::<SampleConfig>(),
        _ => &[],
    }
}

/// Every key the environment can set, by its variable name without the prefix: each key of
/// `ServiceConfig` and of its sections whose value is not a table or a list, and the aliases.
pub fn env_keys() -> Vec<(String, Vec<&'static str>)> {
    let defaults = Table::try_from(ServiceConfig::default()).unwrap_or_default();
    let mut keys = Vec::new();
    for &key in field_names::<ServiceConfig>() {
        match defaults.get(key) {
            Some(Value::Table(section)) => {
                for &sub in section_keys(key) {
                    if !matches!(section.get(sub), Some(Value::Table(_) | Value::Array(_))) {
                        keys.push((sub.to_ascii_uppercase(), vec![key, sub]));
                    }
                }
            }
            Some(Value::Array(_)) => {}
            _ => keys.push((key.to_ascii_uppercase(), vec![key])),
        }
    }
    keys.extend(ENV_ALIASES.iter().map(|(name, path)| ((*name).to_string(), path.to_vec())));
    keys
}

/// One layer: the keys it sets (a path into the tables), `None` = back to the default.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Layer(Vec<(Vec<String>, Option<Value>)>);

impl Layer {
    /// The layer of a serialisable struct of flags: each field given (not `None`) sets the key
    /// of its serde name; a nested struct sets the keys of the section of its name.
    pub fn from_flags<T: Serialize>(flags: &T) -> Result<Self, String> {
        fn walk(prefix: &[String], t: Table, out: &mut Vec<(Vec<String>, Option<Value>)>) {
            for (k, v) in t {
                let mut path = prefix.to_vec();
                path.push(k);
                match v {
                    Value::Table(sub) => walk(&path, sub, out),
                    v => out.push((path, Some(v))),
                }
            }
        }
        let table = Table::try_from(flags).map_err(|e| format!("flags: {e}"))?;
        let mut out = Vec::new();
        walk(&[], table, &mut out);
        Ok(Layer(out))
    }

    /// The layer of the `MPIFLOW_*` variables among `vars`: each value is read as a TOML value
    /// (a number, a boolean) or else as a string, whichever its key accepts; empty = the key's
    /// default (for an optional key: unset), except for the [`NEVER_EMPTY`] security keys, where
    /// it is refused. A value its key does not accept is refused naming the variable and what the
    /// key expects. Variables that name no key are left alone.
    pub fn from_env(vars: impl IntoIterator<Item = (String, String)>) -> Result<Self, String> {
        let keys = env_keys();
        let mut out = Vec::new();
        for (var, raw) in vars {
            let Some(name) = var.strip_prefix(ENV_PREFIX) else { continue };
            let value = raw.trim();
            if name == ENV_SOURCES {
                let datasets: Vec<DatasetConfig> = value
                    .split(',')
                    .filter(|s| !s.trim().is_empty())
                    .map(DatasetConfig::parse)
                    .collect::<Result<_, _>>()
                    .map_err(|e| format!("{var}: {e}"))?;
                let v = Value::try_from(&datasets).map_err(|e| format!("{var}: {e}"))?;
                out.push((vec!["datasets".to_string()], Some(v)));
                continue;
            }
            let Some((_, path)) = keys.iter().find(|(n, _)| n == name) else { continue };
            let path: Vec<String> = path.iter().map(|s| (*s).to_string()).collect();
            if value.is_empty() {
                if path.len() == 1 && NEVER_EMPTY.contains(&path[0].as_str()) {
                    return Err(format!(
                        "{var} is set but empty: a security setting is never turned off by an empty value \
                         (give a value, or unset the variable to keep the configuration file's)"
                    ));
                }
                out.push((path, None));
                continue;
            }
            out.push((path.clone(), Some(typed(&path, value).map_err(|e| format!("{var}={raw:?}: {e}"))?)));
        }
        Ok(Layer(out))
    }

    /// This layer over `config`.
    pub fn apply(&self, config: &ServiceConfig) -> Result<ServiceConfig, String> {
        let mut table = Table::try_from(config).map_err(|e| e.to_string())?;
        if self.0.iter().any(|(p, _)| p.len() == 1 && ONE_OF.contains(&p[0].as_str())) {
            for k in ONE_OF {
                table.remove(k);
            }
        }
        for (path, value) in &self.0 {
            set(&mut table, path, value.clone());
        }
        table.try_into().map_err(|e: toml::de::Error| e.to_string().trim().replace('\n', " "))
    }
}

impl ServiceConfig {
    /// Applies the `MPIFLOW_*` variables among `vars`: `MPIFLOW_` and a key in capitals sets that
    /// key (of the top level, `[models]` or `[sample]`; empty = its default, unset for an
    /// optional key), `MPIFLOW_SOURCES` (comma-separated `NAME=PATH` or `PATH`) replaces the
    /// datasets, `MPIFLOW_PREFETCH` is `default_prefetch` and `MPIFLOW_PRESET` the motion preset
    /// ([`Layer::from_env`]). Other variables (e.g. `MPIFLOW_PHOTOS`, read by the bundled source)
    /// are left alone.
    pub fn apply_env_vars(&mut self, vars: impl IntoIterator<Item = (String, String)>) -> Result<(), String> {
        *self = Layer::from_env(vars)?.apply(self)?;
        Ok(())
    }

    /// Applies a struct of flags: each field given sets the key of its serde name (a nested
    /// struct: the keys of the section of its name).
    pub fn apply_flags<T: Serialize>(&mut self, flags: &T) -> Result<(), String> {
        *self = Layer::from_flags(flags)?.apply(self)?;
        Ok(())
    }
}

/// Sets (or removes, with `None`) the key at `path`, making the sections on the way.
fn set(table: &mut Table, path: &[String], value: Option<Value>) {
    let Some((last, sections)) = path.split_last() else { return };
    let mut t = table;
    for s in sections {
        let entry = t.entry(s.clone()).or_insert_with(|| Value::Table(Table::new()));
        if !entry.is_table() {
            *entry = Value::Table(Table::new());
        }
        let Value::Table(inner) = entry else { return };
        t = inner;
    }
    match value {
        Some(v) => {
            t.insert(last.clone(), v);
        }
        None => {
            t.remove(last);
        }
    }
}

/// `value` as its key at `path` accepts it: as a TOML value (a number, a boolean, ...) if it is
/// one and the key takes it, else as a string, else in lower case (names of presets, kernels and
/// formats are matched ignoring ASCII case); the error is the key's own (what it expects).
fn typed(path: &[String], value: &str) -> Result<Value, String> {
    let literal = format!("v = {value}").parse::<Table>().ok().and_then(|mut t| t.remove("v"));
    let text = [value.to_string(), value.to_ascii_lowercase()].map(Value::String);
    let mut first_error = None;
    for candidate in literal.into_iter().chain(text) {
        let mut alone = Table::new();
        set(&mut alone, path, Some(candidate.clone()));
        match alone.try_into::<ServiceConfig>() {
            Ok(_) => return Ok(candidate),
            Err(e) => {
                first_error.get_or_insert_with(|| e.to_string().trim().replace('\n', " "));
            }
        }
    }
    Err(first_error.unwrap_or_default())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sample::motion::MotionPreset;

    #[test]
    fn every_key_has_one_environment_name() {
        let keys = env_keys();
        let mut names: Vec<&str> = keys.iter().map(|(n, _)| n.as_str()).collect();
        names.sort_unstable();
        let n = names.len();
        names.dedup();
        assert_eq!(names.len(), n, "two keys share an environment name");
        for want in ["WORKERS", "MAX_STREAMS", "TLS_CERT", "AUTH_TOKEN", "PLANES", "DEPTH_MODEL", "MAX_OBJECTS"] {
            assert!(names.contains(&want), "{want} missing from {names:?}");
        }
        // sections and lists are not single variables
        for section in ["MODELS", "SAMPLE", "DATASETS"] {
            assert!(!names.contains(&section), "{section}");
        }
        assert!(field_names::<ServiceConfig>().contains(&"max_buffered_mb"));
    }

    #[test]
    fn a_value_is_typed_by_its_key() {
        let env = |k: &str, v: &str| Layer::from_env([(format!("{ENV_PREFIX}{k}"), v.to_string())]);
        let c = env("AUTH_TOKEN", "12345").unwrap().apply(&ServiceConfig::default()).unwrap();
        assert_eq!(c.auth_token.as_deref(), Some("12345"));
        let c = env("MAX_IMAGE_SIDE", " 640 ").unwrap().apply(&ServiceConfig::default()).unwrap();
        assert_eq!(c.max_image_side, 640);
        let c = env("PRESET", "Paper-KITTI").unwrap().apply(&ServiceConfig::default()).unwrap();
        assert_eq!(c.sample.motion, crate::sample::config::MotionSpec::Preset(MotionPreset::PaperKitti));
        let c = env("LOG_FORMAT", "JSON").unwrap().apply(&ServiceConfig::default()).unwrap();
        assert_eq!(c.log_format, crate::service::config::LogFormat::Json);
        let c = env("AUTH_TOKEN", "AbC").unwrap().apply(&ServiceConfig::default()).unwrap();
        assert_eq!(c.auth_token.as_deref(), Some("AbC"), "a string keeps its case");
        let e = env("WORKERS", "-1").unwrap_err();
        assert!(e.starts_with("MPIFLOW_WORKERS=\"-1\": ") && e.contains("usize"), "{e}");
        let e = env("PREFETCH_SCENES", "yes").unwrap_err();
        assert!(e.starts_with("MPIFLOW_PREFETCH_SCENES=\"yes\": ") && e.contains("bool"), "{e}");
    }
}
