//! MCAP logs (replay, identify, plot, convert read them) on arbitrary bytes: never a panic,
//! never more rows than the bytes could hold, and a refusal is one line.
#![no_main]

use libfuzzer_sys::fuzz_target;
use omnid::telemetry::mcap_log::read::McapTicks;

fuzz_target!(|data: &[u8]| {
    for lenient in [false, true] {
        let mut ticks = McapTicks::new(data, lenient);
        let mut rows = 0usize;
        loop {
            match ticks.next_tick() {
                Ok(Some(_)) => rows += 1,
                Ok(None) => break,
                Err(e) => {
                    assert!(!e.to_string().contains('\n'), "{e}");
                    break;
                }
            }
            assert!(rows <= data.len(), "more rows than bytes");
        }
    }
});
