//! Config files as overrides of defaults: a file's tables merge into the defaults key by key,
//! so a file that sets one field of a section keeps the defaults of its siblings — the
//! defaults of *this* config (e.g. a vision run's or distillation's), not those of the
//! section's type. Options removed from the core are read as gone when a file holds the value
//! every run had, and refused by name otherwise.

use std::borrow::Cow;

use serde::Serialize;
use serde::de::DeserializeOwned;

/// Options removed from the core: the dotted key, the value (TOML) every run had while it
/// existed — `None` when any value was a choice — and the last commit that has the option
/// (docs/notebook/generalist-rejected.md, "Options removed from the core"; the distillation's
/// top-level ones: docs/notebook/vision.md).
const RETIRED: [(&str, Option<&str>, &str); 19] = [
    ("warm_start", None, "9b48c91"),
    ("privileged_critic", Some("false"), "4f9e33d"),
    ("env.obstacle_gates", Some("0"), "4f9e33d"),
    ("env.obstacle_order", Some("\"nearest\""), "4f9e33d"),
    ("env.proximity_gates", Some("0"), "4f9e33d"),
    ("env.proximity_range", Some("4.0"), "4f9e33d"),
    ("env.start_gate", Some("\"first\""), "8941555"),
    ("env.reward.progress_speed_cap", None, "8941555"),
    ("env.randomization.gate_perception", Some("0.0"), "7da1853"),
    ("env.randomization.gate_perception_floor", Some("0.0"), "7da1853"),
    ("crash_margin", Some("0"), "2482eeb"),
    ("gate_loss_weight", Some("0.0"), "2482eeb"),
    ("frozen_encoder", Some("false"), "2482eeb"),
    ("frame_stack", Some("{ frames = 1, stride = 1 }"), "2482eeb"),
    ("frame_widening", Some("\"zero\""), "2482eeb"),
    ("dataset_from", None, "2482eeb"),
    ("relabel", Some("false"), "2482eeb"),
    ("env.controller_model", Some("\"nominal\""), "fd57bb4"),
    ("ppo.clip_per_network", Some("false"), "fd57bb4"),
];

/// Drops, anywhere in a results file written by an earlier commit (`test.json`), every retired
/// option that holds the value every run had: results stay readable after an option leaves the
/// core, while a config file that sets one is still refused by [`retire`].
pub fn retire_in_results(value: &mut serde_json::Value) {
    match value {
        serde_json::Value::Object(fields) => {
            for (key, kept, _) in RETIRED {
                let name = key.rsplit('.').next().unwrap_or(key);
                let kept = kept.and_then(|k| toml::from_str::<toml::Table>(&format!("v = {k}")).ok()).and_then(|t| t.get("v").cloned());
                if let (Some(kept), Some(found)) = (kept, fields.get(name))
                    && serde_json::to_value(&kept).ok().as_ref() == Some(found)
                {
                    fields.remove(name);
                }
            }
            fields.values_mut().for_each(retire_in_results);
        }
        serde_json::Value::Array(items) => items.iter_mut().for_each(retire_in_results),
        _ => {}
    }
}

/// Values removed from an option that stays: the dotted key, the value (TOML) and the last
/// commit that takes it.
const RETIRED_VALUES: [(&str, &str, &str); 1] = [("env.reward.progress_distance", "\"line\"", "fd57bb4")];

/// Why a config file's text cannot be read as overrides of a config's defaults.
#[derive(Debug, thiserror::Error)]
pub enum OverrideError {
    /// Not TOML, an unknown key or a wrong type; toml's message names the line and the key.
    #[error("{0}")]
    Toml(String),
    /// A removed option set to another value than the one every run had.
    #[error(
        "`{key}` was removed from dronerace (a rejected option; it last ran at commit {commit}, and docs/notebook/ says why): delete it from the file"
    )]
    Retired {
        /// Its dotted key.
        key: &'static str,
        /// The last commit that has it.
        commit: &'static str,
    },
    /// A value removed from an option that stays.
    #[error(
        "`{key} = {value}` was removed from dronerace (a rejected choice; it last ran at commit {commit}, and docs/notebook/ says why): choose another value"
    )]
    RetiredValue {
        /// Its dotted key.
        key: &'static str,
        /// The removed value, as TOML.
        value: &'static str,
        /// The last commit that takes it.
        commit: &'static str,
    },
    /// An `[env]` observation key and its `[env.observation]` twin both set.
    #[error("env.{old} and env.observation.{new} are one setting: keep env.observation.{new}")]
    Twice {
        /// The key under `[env]`.
        old: &'static str,
        /// Its name under `[env.observation]`.
        new: &'static str,
    },
    /// `env.observation` is not a table.
    #[error("env.observation must be a table")]
    NotATable,
}

/// toml's error as an [`OverrideError`].
fn toml_error(e: impl std::fmt::Display) -> OverrideError {
    OverrideError::Toml(e.to_string())
}

/// Keys of `[env]` that moved into `[env.observation]` (the one observation layout), with their
/// new names there.
const MOVED: [(&str, &str); 4] =
    [("observation_frame", "frame"), ("line_points", "line_points"), ("line_spacing", "line_spacing"), ("gate_sight", "gate_sight")];

/// `text` without the removed options it holds at the value every run had (a run directory's
/// saved config holds them so), and with `[env]`'s observation keys under `[env.observation]`;
/// a removed option set to anything else is refused by name.
pub fn retire(text: &str) -> Result<Cow<'_, str>, OverrideError> {
    let mut table: toml::Table = toml::from_str(text).map_err(toml_error)?;
    let mut removed = false;
    if let Some(env) = table.get_mut("env").and_then(toml::Value::as_table_mut) {
        for (old, new) in MOVED {
            if let Some(value) = env.remove(old) {
                let observation = env.entry("observation").or_insert_with(|| toml::Value::Table(toml::Table::new()));
                let Some(observation) = observation.as_table_mut() else { return Err(OverrideError::NotATable) };
                if observation.insert(new.to_string(), value).is_some() {
                    return Err(OverrideError::Twice { old, new });
                }
                removed = true;
            }
        }
    }
    for (key, value, commit) in RETIRED_VALUES {
        let (section, last) = section_of(&mut table, key);
        if section.and_then(|s| s.get(last)) == toml_value(value).as_ref() {
            return Err(OverrideError::RetiredValue { key, value, commit });
        }
    }
    for (key, kept, commit) in RETIRED {
        let (section, last) = section_of(&mut table, key);
        let Some(section) = section else { continue };
        let Some(value) = section.get(last) else { continue };
        if kept.and_then(toml_value).as_ref() != Some(value) {
            return Err(OverrideError::Retired { key, commit });
        }
        section.remove(last);
        removed = true;
    }
    Ok(if removed { Cow::Owned(toml::to_string(&table).map_err(toml_error)?) } else { Cow::Borrowed(text) })
}

/// The table that holds dotted `key` in `table` (if every parent is a table) and the key's last part.
fn section_of<'a>(table: &'a mut toml::Table, key: &'a str) -> (Option<&'a mut toml::Table>, &'a str) {
    let (parents, last) = key.rsplit_once('.').map_or((None, key), |(p, l)| (Some(p), l));
    let mut section = Some(table);
    for part in parents.into_iter().flat_map(|p| p.split('.')) {
        section = section.and_then(|s| s.get_mut(part)).and_then(toml::Value::as_table_mut);
    }
    (section, last)
}

/// A TOML value written as text (`"nominal"`, `0.0`, `{ frames = 1 }`).
fn toml_value(text: &str) -> Option<toml::Value> {
    toml::from_str::<toml::Table>(&format!("v = {text}")).ok().and_then(|mut t| t.remove("v"))
}

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
pub fn parse_over<T: Serialize + DeserializeOwned>(defaults: &T, text: &str) -> Result<T, OverrideError> {
    let text = retire(text)?;
    let text = text.as_ref();
    toml::from_str::<T>(text).map_err(toml_error)?;
    let file: toml::Table = toml::from_str(text).map_err(toml_error)?;
    let mut table: toml::Table = toml::from_str(&toml::to_string(defaults).map_err(toml_error)?).map_err(toml_error)?;
    merge(&mut table, &file);
    toml::from_str(&toml::to_string(&table).map_err(toml_error)?).map_err(toml_error)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;
    use taskctl::SwitchParams;

    /// A config whose defaults differ from its sections' types' own, as a distillation's do.
    #[derive(Debug, Serialize, Deserialize)]
    #[serde(deny_unknown_fields, default)]
    struct Tiny {
        rounds: u32,
        switching: SwitchParams,
        env: sim::EnvConfig,
    }

    impl Default for Tiny {
        fn default() -> Self {
            Self {
                rounds: 60,
                switching: SwitchParams { window: 5, alpha: 100.0, ..SwitchParams::default() },
                env: sim::EnvConfig::default(),
            }
        }
    }

    #[test]
    fn a_partial_section_keeps_the_configs_own_defaults_and_bad_keys_are_named() {
        // Tiny's switching default (window 5, α = 100) is not SwitchParams' (600, 1000).
        let config = parse_over(&Tiny::default(), "rounds = 7\n[switching]\npolicy = \"none\"\n").unwrap();
        assert_eq!(config.rounds, 7);
        assert_eq!(config.switching.policy, taskctl::SwitchPolicy::None);
        assert_eq!((config.switching.window, config.switching.alpha), (5, 100.0));
        let err = parse_over(&Tiny::default(), "rounds = 7\n[switching]\nwindoww = 3\n").unwrap_err().to_string();
        assert!(err.contains("windoww") && err.contains("line 3"), "{err}");
    }

    #[test]
    fn a_removed_option_at_its_old_default_is_read_as_gone_and_otherwise_refused_by_name() {
        let saved = "rounds = 7\n[env]\nstart_gate = \"first\"\n[env.randomization]\ngate_perception = 0.0\nmass = 0.1\n";
        let config = parse_over(&Tiny::default(), saved).unwrap();
        assert_eq!((config.rounds, config.env.randomization.mass), (7, 0.1));
        let err = parse_over(&Tiny::default(), "[env]\nstart_gate = \"flying\"\n").unwrap_err().to_string();
        assert!(err.contains("env.start_gate") && err.contains("8941555"), "{err}");
        assert!(retire("[warm_start]\nrounds = 3\n").unwrap_err().to_string().contains("warm_start"));
        // A removed option whose old value is a table (a distillation's frame stack).
        let saved = "rounds = 9\ncrash_margin = 0\n[frame_stack]\nframes = 1\nstride = 1\n";
        assert_eq!(parse_over(&Tiny::default(), saved).unwrap().rounds, 9);
        let err = parse_over(&Tiny::default(), "[frame_stack]\nframes = 4\nstride = 1\n").unwrap_err().to_string();
        assert!(err.contains("frame_stack") && err.contains("2482eeb"), "{err}");
        assert!(matches!(retire("seed = 1\n").unwrap(), Cow::Borrowed(_)), "a file without them is read as written");
        // The observation keys a saved config holds under [env] read as [env.observation]'s.
        let saved = "[env]\nobservation_frame = \"body\"\nline_points = 2\nobstacle_gates = 0\n";
        let config = parse_over(&Tiny::default(), saved).unwrap();
        assert_eq!((config.env.observation.frame, config.env.observation.line_points), (sim::ObservationFrame::Body, 2));
        // The rejected controller model and per-network clipping, and one value of an option.
        let saved = "[env]\ncontroller_model = \"nominal\"\n[ppo]\nclip_per_network = false\n";
        assert!(!retire(saved).unwrap().contains("controller_model"));
        for (text, key) in [
            ("[env]\ncontroller_model = \"compensating\"\n", "env.controller_model"),
            ("[ppo]\nclip_per_network = true\n", "ppo.clip_per_network"),
            ("[env.reward]\nprogress_distance = \"line\"\n", "env.reward.progress_distance"),
        ] {
            let err = retire(text).unwrap_err().to_string();
            assert!(err.contains(key) && err.contains("fd57bb4"), "{err}");
        }
        assert!(retire("[env.reward]\nprogress_distance = \"centre\"\n").is_ok());
        let both = "[env]\nline_points = 2\n[env.observation]\nline_points = 3\n";
        assert!(parse_over(&Tiny::default(), both).unwrap_err().to_string().contains("one setting"));
    }

    #[test]
    fn results_of_earlier_commits_drop_retired_options_that_held_the_kept_value() {
        let mut old = serde_json::json!({ "best": { "config": { "env": { "controller_model": "nominal", "seed": 1 } } }, "x": [{ "clip_per_network": false }] });
        retire_in_results(&mut old);
        assert_eq!(old, serde_json::json!({ "best": { "config": { "env": { "seed": 1 } } }, "x": [{}] }));
        let mut other = serde_json::json!({ "controller_model": "compensating" });
        retire_in_results(&mut other);
        assert!(other.get("controller_model").is_some(), "another value stays, and the reader refuses it");
    }
}
