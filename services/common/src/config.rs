//! Layered configuration: defaults in the `Config` types (serde defaults), then an optional TOML
//! file, then environment variables `DEPTHMILL_<SVC>__SECTION__KEY` (double underscore between
//! levels). Only binaries call [`load`]; libraries take their `Config` as a value.

use std::path::Path;

use serde::de::DeserializeOwned;

/// Why a configuration could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("config file {path} does not exist")]
    Missing { path: String },
    #[error("invalid configuration (file {path}, env prefix {prefix})")]
    Invalid {
        path: String,
        prefix: String,
        #[source]
        source: Box<config::ConfigError>,
    },
}

/// Loads `T` from `file` (if given) and the environment variables that start with `env_prefix`
/// followed by `__` (e.g. `DEPTHMILL_ORCHESTRATOR__REST__ADDR=0.0.0.0:8080`).
/// Unknown keys are an error when `T` denies them (`#[serde(deny_unknown_fields)]`).
pub fn load<T: DeserializeOwned>(file: Option<&Path>, env_prefix: &str) -> Result<T, ConfigError> {
    load_from(file, env_prefix, None)
}

/// [`load`] with the environment given as `(name, value)` pairs instead of the process's: what a
/// binary would load under that environment (deployment tests load the environment a manifest
/// sets, without touching the test process's own).
pub fn load_with_env<T: DeserializeOwned>(
    file: Option<&Path>,
    env_prefix: &str,
    env: impl IntoIterator<Item = (String, String)>,
) -> Result<T, ConfigError> {
    load_from(file, env_prefix, Some(env.into_iter().collect()))
}

fn load_from<T: DeserializeOwned>(
    file: Option<&Path>,
    env_prefix: &str,
    env: Option<config::Map<String, String>>,
) -> Result<T, ConfigError> {
    let mut builder = config::Config::builder();
    let path = file.map(|p| p.display().to_string()).unwrap_or_else(|| "<none>".into());
    if let Some(file) = file {
        if !file.exists() {
            return Err(ConfigError::Missing { path });
        }
        builder = builder.add_source(config::File::from(file).format(config::FileFormat::Toml));
    }
    builder = builder.add_source(
        config::Environment::with_prefix(env_prefix)
            .prefix_separator("__")
            .separator("__")
            .try_parsing(true)
            .source(env),
    );
    builder.build().and_then(|c| c.try_deserialize()).map_err(|source| ConfigError::Invalid {
        path,
        prefix: env_prefix.to_string(),
        source: Box::new(source),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Sample {
        #[serde(default)]
        name: String,
        #[serde(default)]
        port: u16,
    }

    #[test]
    fn file_values_load_and_unknown_keys_are_rejected() {
        let dir = tempfile::tempdir().expect("tempdir");
        let good = dir.path().join("good.toml");
        std::fs::write(&good, "name = \"cam\"\nport = 50053\n").expect("write");
        let s: Sample = load(Some(&good), "DEPTHMILL_TEST_CONFIG_UNUSED").expect("load");
        assert_eq!((s.name.as_str(), s.port), ("cam", 50053));

        let bad = dir.path().join("bad.toml");
        std::fs::write(&bad, "nmae = \"cam\"\n").expect("write");
        let err = load::<Sample>(Some(&bad), "DEPTHMILL_TEST_CONFIG_UNUSED").expect_err("unknown key");
        assert!(crate::ErrorChain(&err).to_string().contains("nmae"), "{}", crate::ErrorChain(&err));

        let missing = load::<Sample>(Some(&dir.path().join("nope.toml")), "X").expect_err("missing");
        assert!(missing.to_string().contains("nope.toml"));
    }

    #[test]
    fn given_environment_overrides_like_the_process_environment() {
        let env = [("DEPTHMILL_SAMPLE__PORT".to_string(), "50051".to_string())];
        let s: Sample = load_with_env(None, "DEPTHMILL_SAMPLE", env).expect("load");
        assert_eq!((s.name.as_str(), s.port), ("", 50051));
        let other_prefix = [("DEPTHMILL_OTHER__PORT".to_string(), "1".to_string())];
        let s: Sample = load_with_env(None, "DEPTHMILL_SAMPLE", other_prefix).expect("load");
        assert_eq!(s.port, 0, "variables of another prefix are ignored");
    }
}
