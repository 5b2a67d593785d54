//! Text for messages: a value quoted back to the user is cut to a readable length (a
//! megabyte-long field must not become a megabyte-long error).

/// Longest quoted value, in characters.
pub const MAX_QUOTED: usize = 80;

/// A number quoted back as the user would write it: `1e308`, not its 309 digits. Text that
/// is not a number, or a short one, is left as it is.
pub fn number(s: &str) -> String {
    match s.trim().parse::<f64>() {
        // Six significant figures, trailing zeros dropped: 999999999999.999 → 1e12.
        Ok(v) if v.is_finite() && s.len() > 12 => {
            let e = format!("{v:.5e}");
            let (mantissa, exponent) = e.split_once('e').unwrap_or((&e, "0"));
            let mantissa = mantissa.trim_end_matches('0').trim_end_matches('.');
            format!("{mantissa}e{exponent}")
        }
        _ => s.to_string(),
    }
}

/// `s` as it is when short, else its first [`MAX_QUOTED`] characters, `…` and its length.
pub fn cut(s: &str) -> String {
    match s.char_indices().nth(MAX_QUOTED) {
        None => s.to_string(),
        Some((end, _)) => format!("{}… ({} bytes)", &s[..end], s.len()),
    }
}

/// Every line of `text` longer than `max` characters cut as [`cut`] does (for messages from
/// other libraries that quote a whole argument back).
pub fn cut_lines(text: &str, max: usize) -> String {
    text.lines()
        .map(|line| match line.char_indices().nth(max) {
            None => line.to_string(),
            Some((end, _)) => format!("{}… ({} bytes)", &line[..end], line.len()),
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// A parser's message about a user's input with each quoted value in it (between backticks
/// or double quotes) cut as [`cut`] does, and the rest kept whole: the user's value is cut,
/// never omnid's own list of choices (`expected one of ...`).
pub fn cut_quoted(message: &str) -> String {
    let mut out = String::with_capacity(message.len().min(4096));
    let mut rest = message;
    while let Some(open) = rest.find(['`', '"']) {
        let quote = &rest[open..open + 1];
        out.push_str(&rest[..=open]);
        rest = &rest[open + 1..];
        match rest.find(quote) {
            Some(close) => {
                out.push_str(&cut(&rest[..close]));
                out.push_str(quote);
                rest = &rest[close + 1..];
            }
            None => {
                out.push_str(&cut(rest));
                rest = "";
            }
        }
    }
    out.push_str(rest);
    out
}

/// `s` with what a terminal would act on instead of showing — control characters (escape
/// sequences) and the marks that reorder text — each replaced by `?`: a value one client gave
/// reaches other users' terminals (in events, in `omnid watch`).
pub fn printable(s: &str) -> String {
    s.chars()
        .map(|c| {
            let reorders = matches!(c, '\u{200e}' | '\u{200f}' | '\u{202a}'..='\u{202e}' | '\u{2066}'..='\u{2069}');
            if c.is_control() || reorders {
                '?'
            } else {
                c
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn huge_numbers_are_quoted_as_written() {
        assert_eq!(number(&1e308f64.to_string()), "1e308");
        assert_eq!(number(&(-2.5e300f64).to_string()), "-2.5e300");
        assert_eq!(number("0.05"), "0.05");
        assert_eq!(number("NaN"), "NaN");
        assert_eq!(number("abc"), "abc");
        assert_eq!(number(&1e-300f64.to_string()), "1e-300");
        assert_eq!(number("999999999999.999"), "1e12");
        assert_eq!(number("123456789.123456"), "1.23457e8");
    }

    #[test]
    fn a_quoted_value_is_cut_and_the_choices_are_kept() {
        let long = "x".repeat(5000);
        let m = format!(
            "unknown variant `{long}`, expected one of `spring`, `damper`, `plane`, `box`, \
             `constant` at line 1 column 5020"
        );
        let c = cut_quoted(&m);
        assert!(c.len() < 300, "{c}");
        assert!(c.contains("(5000 bytes)") && c.ends_with("`constant` at line 1 column 5020"));
        assert_eq!(
            cut_quoted("invalid type: string \"ab\", expected f64"),
            "invalid type: string \"ab\", expected f64"
        );
        // An unclosed quote cuts what follows it.
        assert!(cut_quoted(&format!("bad `{long}")).len() < 200);
    }

    #[test]
    fn what_a_terminal_would_act_on_is_shown_as_question_marks() {
        assert_eq!(printable("lab \u{1b}[2J\u{202e}arm\tx"), "lab ?[2J?arm?x");
        assert_eq!(printable("PHANToM 1 ü"), "PHANToM 1 ü");
    }

    #[test]
    fn short_values_stay_long_ones_are_cut_on_a_character_boundary() {
        assert_eq!(cut("abc"), "abc");
        let long = "é".repeat(1000);
        let c = cut(&long);
        assert!(c.starts_with(&"é".repeat(MAX_QUOTED)));
        assert!(c.ends_with("… (2000 bytes)"), "{c}");
        assert!(c.chars().count() < MAX_QUOTED + 20);
    }
}
