//! Scene files (`omnid run --scene FILE`): the effects in TOML, one `[[effect]]` table each
//! (docs/HAPTICS.md §8). Read and checked before the run; errors name the line or the field.

use super::effects::{Effect, MAX_EFFECTS};
use serde::Deserialize;
use std::path::Path;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneFile {
    #[serde(default)]
    effect: Vec<Effect>,
}

/// The effects of the scene in `text` (`name` for messages); a refusal is one line naming
/// the scene, the line and column (`crate::toml_place`), the key (`effect[1].normal`) and what
/// is wrong.
pub fn parse_scene(text: &str, name: &str) -> Result<Vec<Effect>, String> {
    use crate::toml_place::{place_of, Part};
    let file: SceneFile =
        toml::from_str(text).map_err(|e| format!("scene {name}: {}", effect_error(text, &e)))?;
    if file.effect.len() > MAX_EFFECTS {
        let at = place_of(text, &format!("effect[{MAX_EFFECTS}]"), Part::Value)
            .map(|p| format!("{p}: "))
            .unwrap_or_default();
        return Err(format!(
            "scene {name}: {at}{} effects; at most {MAX_EFFECTS}",
            file.effect.len()
        ));
    }
    for (i, e) in file.effect.iter().enumerate() {
        let prefix = format!("effect[{i}].");
        e.validate(&prefix).map_err(|m| {
            // The message starts with the key (`effect[1].stiffness_n_per_mm = ...`).
            let key: String = m
                .chars()
                .take_while(|c| !c.is_whitespace() && *c != '=' && *c != ':')
                .collect();
            match place_of(text, &key, Part::Value) {
                Some(p) => format!("scene {name}: {p}: {m}"),
                None => format!("scene {name}: {m}"),
            }
        })?;
    }
    Ok(file.effect)
}

/// A parse error of a scene at its true place. An `[[effect]]` is read through its `type`
/// (an internally tagged enum), so the parser's own error points at the whole list of effects
/// (line 1) and its message does not name the key: each effect is read again alone, and the
/// key found that the error is about (named in the message, else the one whose removal
/// changes the error).
fn effect_error(text: &str, e: &toml::de::Error) -> String {
    use crate::toml_place::{describe, field_in_message, place_of, Part};
    use serde::de::Deserialize;
    let Ok(table) = toml::from_str::<toml::Table>(text) else {
        return describe(text, e);
    };
    let Some(effects) = table.get("effect").and_then(|v| v.as_array()) else {
        return describe(text, e);
    };
    let read = |t: &toml::Table| Effect::deserialize(toml::Value::Table(t.clone()));
    for (i, value) in effects.iter().enumerate() {
        let Some(t) = value.as_table() else { continue };
        let Err(err) = read(t) else { continue };
        let message = crate::text::cut_quoted(&err.message().trim().replace('\n', " "));
        let (key, part) = match field_in_message(&message) {
            Some(f) => (f.to_string(), Part::Key),
            // A key that is not there: the effect's own header.
            None if message.contains("missing field") => {
                let at = place_of(text, &format!("effect[{i}]"), Part::Value)
                    .map(|p| format!("{p}: "))
                    .unwrap_or_default();
                return format!("{at}effect[{i}]: {message}");
            }
            None => {
                let culprit = t.keys().find(|k| {
                    let mut without = t.clone();
                    without.remove(*k);
                    read(&without).map_err(|e| e.message().to_string()).err()
                        != Some(err.message().to_string())
                });
                (
                    culprit.cloned().unwrap_or_else(|| "type".into()),
                    Part::Value,
                )
            }
        };
        let path = format!("effect[{i}].{key}");
        let at = place_of(text, &path, part)
            .or_else(|| place_of(text, &format!("effect[{i}]"), Part::Value));
        return match at {
            Some(p) => format!("{p}: {path}: {message}"),
            None => format!("{path}: {message}"),
        };
    }
    describe(text, e)
}

/// Read and check a scene file (at most 1 MiB).
pub fn read_scene(
    path: &Path,
    stop: Option<&std::sync::Arc<std::sync::atomic::AtomicBool>>,
) -> Result<Vec<Effect>, String> {
    let name = path.display().to_string();
    // Capped however the file reports its size (a FIFO or /dev/zero says 0), and a pipe is
    // waited on only with the operator's stop flag (crate::input).
    let text = crate::input::read_capped(path, MAX_SCENE_BYTES, stop)
        .map_err(|e| format!("cannot read scene {name}: {e}"))?;
    parse_scene(&text, &name)
}

/// The largest scene file read.
const MAX_SCENE_BYTES: u64 = 1 << 20;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scene_reads_several_effects() {
        let text = r#"
[[effect]]
type = "plane"
point_mm = [0, -20, 0]
normal = [0, 1, 0]
stiffness_n_per_mm = 1.0
damping_n_s_per_m = 2.0

[[effect]]
type = "damper"
damping_n_s_per_m = 1.5
"#;
        let effects = parse_scene(text, "s.toml").unwrap();
        assert_eq!(effects.len(), 2);
        assert_eq!(
            effects[1],
            Effect::Damper {
                damping_n_s_per_m: 1.5
            }
        );
    }

    #[test]
    fn bad_scenes_name_the_line_or_the_field() {
        let e = parse_scene("[[effect]]\ntype = \"wobble\"\n", "s.toml").unwrap_err();
        assert!(e.contains("line 2") && e.contains("wobble"), "{e}");
        let e = parse_scene(
            "[[effect]]\ntype = \"damper\"\ndamping_n_s_per_m = 1\ncolour = 2\n",
            "s.toml",
        )
        .unwrap_err();
        assert!(e.contains("colour"), "{e}");
        let e = parse_scene(
            "[[effect]]\ntype = \"spring\"\ncenter_mm = [0,0,0]\nstiffness_n_per_mm = -1\n",
            "s.toml",
        )
        .unwrap_err();
        assert!(e.contains("effect[0].stiffness_n_per_mm"), "{e}");
    }
}
