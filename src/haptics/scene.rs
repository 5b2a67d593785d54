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
/// the scene and where.
pub fn parse_scene(text: &str, name: &str) -> Result<Vec<Effect>, String> {
    let file: SceneFile = toml::from_str(text).map_err(|e| {
        let line = e
            .span()
            .map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1);
        let what = e.message().trim().replace('\n', " ");
        match line {
            Some(l) => format!("scene {name}: line {l}: {what}"),
            None => format!("scene {name}: {what}"),
        }
    })?;
    if file.effect.len() > MAX_EFFECTS {
        return Err(format!(
            "scene {name}: {} effects; at most {MAX_EFFECTS}",
            file.effect.len()
        ));
    }
    for (i, e) in file.effect.iter().enumerate() {
        e.validate(&format!("effect[{i}]."))
            .map_err(|m| format!("scene {name}: {m}"))?;
    }
    Ok(file.effect)
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
