//! Config files as overrides of defaults: a file's tables merge into the defaults key by key,
//! so a file that sets one field of a section keeps the defaults of its siblings — the
//! defaults of *this* config (e.g. a vision run's or distillation's), not those of the
//! section's type.

use serde::Serialize;
use serde::de::DeserializeOwned;

/// Merges `overrides` into `table`: tables key by key, anything else replaced.
pub fn merge(table: &mut toml::Table, overrides: &toml::Table) {
    for (key, value) in overrides {
        match (table.get_mut(key), value) {
            (Some(toml::Value::Table(existing)), toml::Value::Table(inner)) => merge(existing, inner),
            _ => {
                table.insert(key.clone(), value.clone());
            }
        }
    }
}

/// Parses `text` as overrides of `defaults`. The text is first parsed on its own, so that an
/// unknown key or a wrong type is reported with its line.
pub fn parse_over<T: Serialize + DeserializeOwned>(defaults: &T, text: &str) -> Result<T, String> {
    toml::from_str::<T>(text).map_err(|e| e.to_string())?;
    let file: toml::Table = toml::from_str(text).map_err(|e| e.to_string())?;
    let mut table: toml::Table = toml::from_str(&toml::to_string(defaults).map_err(|e| e.to_string())?).map_err(|e| e.to_string())?;
    merge(&mut table, &file);
    toml::from_str(&toml::to_string(&table).map_err(|e| e.to_string())?).map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::distill::DistillConfig;

    #[test]
    fn a_partial_section_keeps_the_configs_own_defaults_and_bad_keys_are_named() {
        // DistillConfig's switching default (window 5, α = 100) is not SwitchParams' (600, 1000).
        let config = parse_over(&DistillConfig::default(), "rounds = 7\n[switching]\npolicy = \"none\"\n").unwrap();
        assert_eq!(config.rounds, 7);
        assert_eq!(config.switching.policy, taskctl::SwitchPolicy::None);
        assert_eq!((config.switching.window, config.switching.alpha), (5, 100.0));
        assert_eq!(config.envs, DistillConfig::default().envs);
        let err = parse_over(&DistillConfig::default(), "rounds = 7\n[switching]\nwindoww = 3\n").unwrap_err();
        assert!(err.contains("windoww") && err.contains("line 3"), "{err}");
    }
}
