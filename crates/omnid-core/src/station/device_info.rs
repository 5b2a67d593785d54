//! What the daemon tells clients about the device beyond the joint angles: its
//! identification (the hello) and its gimbal angles (the state stream). docs/HDAPI.md says
//! how OpenHaptics-style clients read them.

use std::f64::consts::PI;

/// The Omni's maker, as the device identifies itself to the vendor's tools.
pub const VENDOR: &str = "SensAble Technologies";

/// Pot word at the middle of the gimbal's travel: reported as 0 rad.
const MID_SCALE: f64 = 32768.0;

/// The model name for a device kind (`sim`, `replay`, `usb`, `firewire`).
pub fn model(device: &str) -> &'static str {
    match device {
        "sim" => "PHANTOM Omni (omnid simulator)",
        "replay" => "PHANTOM Omni (omnid replay)",
        _ => "PHANTOM Omni",
    }
}

/// Gimbal angles, rad, from the three potentiometer words. Nominal and uncalibrated: the
/// pots' full 16-bit scale spans one turn centred on mid-scale (0 rad), because no open
/// source documents the pots' gain or offsets; the simulator reports mid-scale. Only the
/// upper 11 bits carry information (docs/FIREWIRE.md §4), so the lower 5 are dropped.
pub fn gimbal_angles(words: [u16; 3]) -> [f64; 3] {
    words.map(|w| (f64::from(w & 0xFFE0) - MID_SCALE) / MID_SCALE * PI)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mid_scale_is_zero_and_the_scale_is_one_turn() {
        assert_eq!(gimbal_angles([0x8000; 3]), [0.0; 3]);
        let a = gimbal_angles([0x4000, 0xC000, 0x801F]);
        assert!((a[0] + PI / 2.0).abs() < 1e-12 && (a[1] - PI / 2.0).abs() < 1e-12);
        assert_eq!(a[2], 0.0, "the low 5 bits carry nothing");
    }
}
