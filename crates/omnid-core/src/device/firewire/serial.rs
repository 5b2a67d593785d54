//! The Omni's serial number (docs/FIREWIRE.md §2): the quadlet at 0x10060010 packs the
//! 11 digits printed on the unit's label. Layout from the ROS driver (omnifirewire.cpp:496-518
//! unpacks, :335-359 packs): bit 31 and bit 0 set, then from bit 25 down
//! `a` (3 bits, 1 digit), `b` (4 bits, 2 digits), `c` (5 bits, 2 digits), `d` (3 bits,
//! 1 digit), `e` (10 bits, 5 digits).

/// The fixed bits of a packed serial (omnifirewire.cpp:352: `0x80000001`).
const FRAME: u32 = 0x8000_0001;
/// Bits no field uses (30..26): zero in every packed serial.
const UNUSED: u32 = 0x7C00_0000;

/// The 11-digit label form of a serial quadlet, or `None` when the quadlet is not a packed
/// serial (its fixed bits are wrong).
pub(crate) fn label(quadlet: u32) -> Option<String> {
    if quadlet & FRAME != FRAME || quadlet & UNUSED != 0 {
        return None;
    }
    let a = (quadlet >> 23) & 0x7;
    let b = (quadlet >> 19) & 0xF;
    let c = (quadlet >> 14) & 0x1F;
    let d = (quadlet >> 11) & 0x7;
    let e = (quadlet >> 1) & 0x3FF;
    Some(format!("{a:01}{b:02}{c:02}{d:01}{e:05}"))
}

/// How omnid names a unit: the label form, or `0x` and the raw quadlet when it does not
/// decode (calibrations are stored under this name).
pub(crate) fn name(quadlet: u32) -> String {
    label(quadlet).unwrap_or_else(|| format!("0x{quadlet:08x}"))
}

/// Why a configured serial cannot be an Omni's.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct SerialFormatError(pub String);

/// The quadlet a configured serial stands for: the 11-digit label form, or `0x` and eight hex
/// digits (the raw quadlet, as [`name`] prints a unit whose quadlet does not decode).
pub(crate) fn parse(text: &str) -> Result<u32, SerialFormatError> {
    if let Some(hex) = text.strip_prefix("0x") {
        if hex.len() == 8 {
            if let Ok(q) = u32::from_str_radix(hex, 16) {
                return Ok(q);
            }
        }
        return Err(SerialFormatError(
            "0x and eight hex digits (the raw serial quadlet)".into(),
        ));
    }
    if text.len() != 11 || !text.bytes().all(|b| b.is_ascii_digit()) {
        return Err(SerialFormatError(
            "the 11 digits on the unit's label (or 0x and eight hex digits)".into(),
        ));
    }
    let field = |from: usize, to: usize| -> u32 {
        text[from..to]
            .bytes()
            .fold(0u32, |v, b| v * 10 + u32::from(b - b'0'))
    };
    let groups = [
        ("a (digit 1)", field(0, 1), 0x7, 23),
        ("b (digits 2-3)", field(1, 3), 0xF, 19),
        ("c (digits 4-5)", field(3, 5), 0x1F, 14),
        ("d (digit 6)", field(5, 6), 0x7, 11),
        ("e (digits 7-11)", field(6, 11), 0x3FF, 1),
    ];
    let mut q = FRAME;
    for (what, value, max, shift) in groups {
        if value > max {
            return Err(SerialFormatError(format!(
                "a serial the Omni can report: group {what} is {value}, at most {max} \
                 (omnifirewire.cpp:496-518)"
            )));
        }
        q |= value << shift;
    }
    Ok(q)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn label_round_trips_through_the_packed_quadlet() {
        // Digits a=1, b=02, c=03, d=4, e=00567, packed by hand from the layout.
        let q = 0x8000_0001 | (1 << 23) | (2 << 19) | (3 << 14) | (4 << 11) | (567 << 1);
        assert_eq!(label(q).as_deref(), Some("10203400567"));
        assert_eq!(parse("10203400567"), Ok(q));
        // Largest value of every group.
        let max = parse("71531701023").unwrap();
        assert_eq!(max, 0x83FF_FFFF);
        assert_eq!(label(max).as_deref(), Some("71531701023"));
    }

    #[test]
    fn quadlets_that_are_not_packed_serials_get_the_raw_name() {
        assert_eq!(label(31337), None);
        assert_eq!(name(31337), "0x00007a69");
        assert_eq!(parse("0x00007a69"), Ok(31337));
        // A bit in 30..26 set.
        assert_eq!(label(0x8400_0001), None);
    }

    #[test]
    fn bad_serials_say_what_is_wrong() {
        for (bad, says) in [
            ("1234", "11 digits"),
            ("1234567890a", "11 digits"),
            ("81234567890", "group a (digit 1) is 8"),
            ("11634567890", "group b (digits 2-3) is 16"),
            ("10299901024", "group c (digits 4-5) is 99"),
            ("10203401024", "group e (digits 7-11) is 1024"),
            ("0x123", "eight hex digits"),
        ] {
            let e = parse(bad).unwrap_err().0;
            assert!(e.contains(says), "{bad}: {e}");
        }
    }
}
