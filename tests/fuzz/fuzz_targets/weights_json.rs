//! The identifier's weights file (`--weights`) on arbitrary UTF-8: never a panic, and a file it
//! accepts writes and reads back to itself.
#![no_main]

use libfuzzer_sys::fuzz_target;
use omnid::identifier::WeightsFile;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(w) = WeightsFile::from_json(text, "fuzz.json") {
        let back = WeightsFile::from_json(&w.to_json(), "again.json").expect("round trip parses");
        assert_eq!(back, w);
    }
});
