//! Where in a TOML file (a config, a scene) something is: the line and column of a byte
//! offset, of a dotted key's value or of the key itself, and a TOML parser's error told at its
//! place. One place for both the config and scene files, so their errors read alike: `line 7,
//! column 22 (`stiffness_n_per_mm = -3`): ...`. The line quoted back is the user's text, cut
//! as [`crate::text::cut`] cuts (with its length).

use std::ops::Range;

/// A place in a file, for a message: `line L, column C (`the line`)`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Place {
    /// 1-based line.
    pub line: usize,
    /// 1-based column, in characters.
    pub column: usize,
    /// The line's text, trimmed and cut.
    pub excerpt: String,
}

impl std::fmt::Display for Place {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "line {}, column {} (`{}`)",
            self.line, self.column, self.excerpt
        )
    }
}

/// The place of byte `offset` of `text` (clamped to the text, and back to a character's start).
pub fn place_at(text: &str, offset: usize) -> Place {
    let mut offset = offset.min(text.len());
    while !text.is_char_boundary(offset) {
        offset -= 1;
    }
    let line_start = text[..offset].rfind('\n').map_or(0, |i| i + 1);
    let line_end = text[offset..].find('\n').map_or(text.len(), |i| offset + i);
    Place {
        line: text[..offset].matches('\n').count() + 1,
        column: text[line_start..offset].chars().count() + 1,
        excerpt: crate::text::cut(text[line_start..line_end].trim()),
    }
}

/// What of a key to point at.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Part {
    /// The key itself (a key that should not be there).
    Key,
    /// Its value (a value out of range or of the wrong type).
    Value,
}

/// The byte range of `path` in `text`: a dotted key whose parts may be indexed, as messages
/// name fields (`haptics.max_force_n`, `effect[1].stiffness_n_per_mm`, `arm[0].name`). None
/// when the text does not parse or does not hold it (a default, or a computed field).
pub fn span_of(text: &str, path: &str, part: Part) -> Option<Range<usize>> {
    let doc = toml_edit::ImDocument::parse(text).ok()?;
    let mut steps: Vec<(&str, Vec<usize>)> = Vec::new();
    for seg in path.split('.') {
        let (name, rest) = seg.split_once('[').unwrap_or((seg, ""));
        let mut indices = Vec::new();
        for i in rest.split('[') {
            let i = i.trim_end_matches(']');
            if !i.is_empty() {
                indices.push(i.parse().ok()?);
            }
        }
        steps.push((name, indices));
    }
    let mut item = doc.as_item();
    let last = steps.len().checked_sub(1)?;
    for (k, (name, indices)) in steps.iter().enumerate() {
        let parent = item;
        item = item.get(*name)?;
        if k == last && indices.is_empty() && part == Part::Key {
            return parent.as_table_like()?.key(name)?.span();
        }
        for i in indices {
            item = item.get(*i)?;
        }
    }
    item.span()
}

/// The place of `path` (see [`span_of`]).
pub fn place_of(text: &str, path: &str, part: Part) -> Option<Place> {
    span_of(text, path, part).map(|s| place_at(text, s.start))
}

/// The dotted key (`sim.substeps`, `effect[1].normal[2]`) of the innermost value of `text`
/// whose span holds byte `offset`; None outside every value (or when the text does not parse).
pub fn path_at(text: &str, offset: usize) -> Option<String> {
    fn value(v: &toml_edit::Value, offset: usize, path: String) -> Option<String> {
        if !v.span().is_some_and(|s| s.contains(&offset)) {
            return None;
        }
        let inner = match v {
            toml_edit::Value::Array(a) => a
                .iter()
                .enumerate()
                .find_map(|(i, x)| value(x, offset, format!("{path}[{i}]"))),
            toml_edit::Value::InlineTable(t) => t
                .iter()
                .find_map(|(k, x)| value(x, offset, format!("{path}.{k}"))),
            _ => None,
        };
        Some(inner.unwrap_or(path))
    }
    fn table(t: &toml_edit::Table, offset: usize, path: &str) -> Option<String> {
        let dot = if path.is_empty() { "" } else { "." };
        t.iter()
            .find_map(|(k, x)| item(x, offset, format!("{path}{dot}{k}")))
    }
    fn item(i: &toml_edit::Item, offset: usize, path: String) -> Option<String> {
        match i {
            toml_edit::Item::Value(v) => value(v, offset, path),
            toml_edit::Item::Table(t) => table(t, offset, &path),
            toml_edit::Item::ArrayOfTables(a) => a
                .iter()
                .enumerate()
                .find_map(|(k, t)| table(t, offset, &format!("{path}[{k}]"))),
            toml_edit::Item::None => None,
        }
    }
    let doc = toml_edit::ImDocument::parse(text).ok()?;
    table(doc.as_table(), offset, "")
}

/// A TOML parser's error in one line, told at its place: `line L, column C (`the line`):
/// `the.key`: message` (the key where the message does not name one). The message's quoted
/// values are cut ([`crate::text::cut_quoted`]); its lists of what is expected are kept whole.
pub fn describe(text: &str, e: &toml::de::Error) -> String {
    let message = crate::text::cut_quoted(&e.message().trim().replace('\n', " "));
    match e.span() {
        Some(span) => {
            let key = match field_in_message(&message) {
                Some(_) => None,
                None => path_at(text, span.start),
            };
            format!(
                "{}: {}{message}",
                place_at(text, span.start),
                key.map(|k| format!("`{k}`: ")).unwrap_or_default()
            )
        }
        None => message,
    }
}

/// The key a serde message is about: `unknown field `x``, `missing field `x``, `duplicate
/// field `x``.
pub fn field_in_message(message: &str) -> Option<&str> {
    for lead in ["unknown field `", "duplicate field `"] {
        if let Some(at) = message.find(lead) {
            let rest = &message[at + lead.len()..];
            return rest.find('`').map(|end| &rest[..end]);
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEXT: &str = "[sim]\nsubsteps = 3\n\n[[effect]]\ntype = \"damper\"\n\n[[effect]]\ntype = \"plane\"\nnormal = [0, 1, 0]\n  stiffness_n_per_mm = -3\n";

    #[test]
    fn places_are_lines_and_columns_of_the_user_text() {
        let p = place_at("a = 1\nb = 2\n", 10);
        assert_eq!((p.line, p.column, p.excerpt.as_str()), (2, 5, "b = 2"));
        // Columns count characters, not bytes; an offset inside one goes back to its start.
        let p = place_at("k = \"éé\" x", 8);
        assert_eq!((p.line, p.column), (1, 7));
        assert_eq!(place_at("", 10).line, 1);
        // A long line is cut with its length.
        let long = format!("k = \"{}\"", "x".repeat(500));
        assert!(place_at(&long, 0).excerpt.contains("(506 bytes)"));
    }

    #[test]
    fn dotted_and_indexed_keys_are_found() {
        let v = place_of(TEXT, "effect[1].stiffness_n_per_mm", Part::Value).unwrap();
        assert_eq!((v.line, v.column), (10, 24), "{v}");
        let k = place_of(TEXT, "effect[1].stiffness_n_per_mm", Part::Key).unwrap();
        assert_eq!((k.line, k.column), (10, 3), "{k}");
        let s = place_of(TEXT, "sim.substeps", Part::Value).unwrap();
        assert_eq!((s.line, s.column), (2, 12));
        let n = place_of(TEXT, "effect[1].normal[2]", Part::Value).unwrap();
        assert_eq!((n.line, n.column), (9, 17));
        assert_eq!(place_of(TEXT, "effect[2].type", Part::Value), None);
        assert_eq!(place_of(TEXT, "haptics.max_force_n", Part::Value), None);
        assert_eq!(place_of("not toml [", "a", Part::Value), None);
        let at = |path: &str| span_of(TEXT, path, Part::Value).unwrap().start;
        for path in [
            "sim.substeps",
            "effect[1].normal[2]",
            "effect[1].stiffness_n_per_mm",
        ] {
            assert_eq!(path_at(TEXT, at(path)).as_deref(), Some(path));
        }
        assert_eq!(path_at(TEXT, 0), None);
    }

    #[test]
    fn a_type_error_names_its_key_and_place() {
        #[derive(Debug, serde::Deserialize)]
        #[allow(dead_code)]
        struct Sim {
            substeps: u32,
        }
        #[derive(Debug, serde::Deserialize)]
        #[allow(dead_code)]
        struct File {
            sim: Sim,
        }
        let text = "\n[sim]\nsubsteps = \"three\"\n";
        let e = toml::from_str::<File>(text).unwrap_err();
        assert_eq!(
            describe(text, &e),
            "line 3, column 12 (`substeps = \"three\"`): `sim.substeps`: invalid type: string \"three\", expected u32"
        );
    }

    #[test]
    fn fields_are_read_from_serde_messages() {
        assert_eq!(
            field_in_message("unknown field `colour`, expected one of `a`, `b`"),
            Some("colour")
        );
        assert_eq!(field_in_message("invalid type: string \"x\""), None);
    }
}
