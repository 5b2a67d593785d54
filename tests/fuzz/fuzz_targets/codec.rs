//! The packet decoders on arbitrary bytes: never a panic, and whatever decodes re-encodes to a
//! packet that decodes to the same value.
#![no_main]

use libfuzzer_sys::fuzz_target;
use omnid::device::codec::{
    decode_command, decode_state, encode_command, encode_state, COMMAND_LEN, STATE_LEN,
};

fuzz_target!(|data: &[u8]| {
    match decode_state(data) {
        Ok(s) => assert_eq!(decode_state(&encode_state(&s)), Ok(s)),
        Err(_) => assert_ne!(
            data.len(),
            STATE_LEN,
            "a {STATE_LEN}-byte state packet always decodes"
        ),
    }
    if let Ok(c) = decode_command(data) {
        assert_eq!(data.len(), COMMAND_LEN);
        assert_eq!(decode_command(&encode_command(&c)), Ok(c));
    }
});
