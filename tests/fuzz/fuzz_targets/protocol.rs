//! A client's message as the daemon's hub reads it, on arbitrary bytes: never a panic, and a
//! refusal is one line of bounded length (a megabyte of input never becomes a megabyte of
//! error sent back).
#![no_main]

use libfuzzer_sys::fuzz_target;
use omnid::transport::json::decode_request;

fuzz_target!(|data: &[u8]| {
    if let Err(e) = decode_request(data) {
        assert!(!e.contains('\n'), "multi-line refusal: {e}");
        assert!(e.len() < 2048, "refusal of {} bytes", e.len());
    }
});
