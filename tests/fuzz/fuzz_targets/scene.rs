//! Haptic scene files (`--scene`) on arbitrary UTF-8: never a panic, a refusal is one line that
//! names the scene, and every effect of an accepted scene has finite values.
#![no_main]

use libfuzzer_sys::fuzz_target;
use omnid::haptics::scene::parse_scene;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    match parse_scene(text, "fuzz.toml") {
        Ok(effects) => {
            let json = serde_json::to_string(&effects).expect("effects serialise");
            assert!(!json.contains("null"), "a non-finite value was accepted: {json}");
        }
        Err(e) => {
            assert!(!e.contains('\n') && e.contains("fuzz.toml"), "{e}");
        }
    }
});
