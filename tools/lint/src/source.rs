//! Rust source reduced to what the checks read: comments and literal contents blanked out,
//! `#[cfg(test)]` items removed, then split into tokens.

/// A token: an identifier or keyword, a `::`, or any other single character.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Tok {
    Ident(String),
    PathSep,
    Punct(char),
    /// A string literal, contents kept (the error-message check reads them).
    Str(String),
}

fn is_ident_start(c: char) -> bool {
    c.is_alphabetic() || c == '_'
}

fn is_ident(c: char) -> bool {
    c.is_alphanumeric() || c == '_'
}

/// Tokens of `text`, comments dropped, char literals and numbers skipped.
pub fn tokenize(text: &str) -> Vec<Tok> {
    let c: Vec<char> = text.chars().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < c.len() {
        let ch = c[i];
        if ch.is_whitespace() {
            i += 1;
        } else if ch == '/' && c.get(i + 1) == Some(&'/') {
            while i < c.len() && c[i] != '\n' {
                i += 1;
            }
        } else if ch == '/' && c.get(i + 1) == Some(&'*') {
            let mut depth = 0;
            while i < c.len() {
                if c[i] == '/' && c.get(i + 1) == Some(&'*') {
                    depth += 1;
                    i += 2;
                } else if c[i] == '*' && c.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    i += 1;
                }
            }
        } else if let Some((s, next)) = raw_string(&c, i) {
            out.push(Tok::Str(s));
            i = next;
        } else if ch == '"' || (ch == 'b' && c.get(i + 1) == Some(&'"')) {
            let mut j = if ch == 'b' { i + 2 } else { i + 1 };
            let mut s = String::new();
            while j < c.len() && c[j] != '"' {
                if c[j] == '\\' && j + 1 < c.len() {
                    s.push(c[j]);
                    j += 1;
                }
                s.push(c[j]);
                j += 1;
            }
            out.push(Tok::Str(s));
            i = j + 1;
        } else if ch == '\'' {
            // A char literal ('a', '\n', '\u{..}') or a lifetime / label ('a).
            if c.get(i + 1) == Some(&'\\') {
                let mut j = i + 2;
                while j < c.len() && c[j] != '\'' {
                    j += 1;
                }
                i = j + 1;
            } else if c.get(i + 2) == Some(&'\'') {
                i += 3;
            } else {
                i += 1;
            }
        } else if ch.is_ascii_digit() {
            while i < c.len() && (is_ident(c[i]) || c[i] == '.') {
                // `1..n`: stop before a range.
                if c[i] == '.' && c.get(i + 1) == Some(&'.') {
                    break;
                }
                i += 1;
            }
        } else if is_ident_start(ch) {
            let start = i;
            while i < c.len() && is_ident(c[i]) {
                i += 1;
            }
            out.push(Tok::Ident(c[start..i].iter().collect()));
        } else if ch == ':' && c.get(i + 1) == Some(&':') {
            out.push(Tok::PathSep);
            i += 2;
        } else {
            out.push(Tok::Punct(ch));
            i += 1;
        }
    }
    out
}

/// `r"..."`, `r#"..."#`, `br"..."` starting at `i`: the contents and the index after it.
fn raw_string(c: &[char], i: usize) -> Option<(String, usize)> {
    if i > 0 && is_ident(c[i - 1]) {
        return None;
    }
    let mut j = i;
    if c.get(j) == Some(&'b') {
        j += 1;
    }
    if c.get(j) != Some(&'r') {
        return None;
    }
    j += 1;
    let mut hashes = 0;
    while c.get(j) == Some(&'#') {
        hashes += 1;
        j += 1;
    }
    if c.get(j) != Some(&'"') {
        return None;
    }
    j += 1;
    let start = j;
    while j < c.len() {
        if c[j] == '"' && (0..hashes).all(|k| c.get(j + 1 + k) == Some(&'#')) {
            return Some((c[start..j].iter().collect(), j + 1 + hashes));
        }
        j += 1;
    }
    Some((c[start..].iter().collect(), c.len()))
}

/// The tokens without items marked `#[cfg(test)]` (test modules, test-only functions and
/// imports). Also reports the names of `#[cfg(test)] mod NAME;` declarations, whose files are
/// test code too.
pub fn without_test_items(toks: &[Tok]) -> (Vec<Tok>, Vec<String>) {
    let mut out = Vec::with_capacity(toks.len());
    let mut test_mods = Vec::new();
    let mut i = 0;
    while i < toks.len() {
        if is_cfg_test(toks, i) {
            // Skip the attribute, any further attributes, then the item.
            let mut j = i + 7;
            while toks.get(j) == Some(&Tok::Punct('#')) {
                j = skip_attribute(toks, j);
            }
            if let (Some(Tok::Ident(m)), Some(Tok::Ident(name))) = (toks.get(j), toks.get(j + 1)) {
                if m == "mod" && toks.get(j + 2) == Some(&Tok::Punct(';')) {
                    test_mods.push(name.clone());
                }
            }
            i = skip_item(toks, j);
            continue;
        }
        out.push(toks[i].clone());
        i += 1;
    }
    (out, test_mods)
}

/// `# [ cfg ( test ) ]` at `i`.
fn is_cfg_test(toks: &[Tok], i: usize) -> bool {
    let want = [
        Tok::Punct('#'),
        Tok::Punct('['),
        Tok::Ident("cfg".into()),
        Tok::Punct('('),
        Tok::Ident("test".into()),
        Tok::Punct(')'),
        Tok::Punct(']'),
    ];
    toks.len() >= i + want.len() && toks[i..i + want.len()] == want
}

fn skip_attribute(toks: &[Tok], i: usize) -> usize {
    // `#` `[` ... `]` with nesting.
    let mut depth = 0;
    let mut j = i + 1;
    while j < toks.len() {
        match toks[j] {
            Tok::Punct('[') => depth += 1,
            Tok::Punct(']') => {
                depth -= 1;
                if depth == 0 {
                    return j + 1;
                }
            }
            _ => {}
        }
        j += 1;
    }
    j
}

/// The index after the item starting at `i`: up to its `;` or its balanced `{ ... }` body.
fn skip_item(toks: &[Tok], i: usize) -> usize {
    let mut j = i;
    let mut paren = 0i32;
    while j < toks.len() {
        match toks[j] {
            Tok::Punct('(') | Tok::Punct('[') => paren += 1,
            Tok::Punct(')') | Tok::Punct(']') => paren -= 1,
            Tok::Punct(';') if paren == 0 => return j + 1,
            Tok::Punct('{') if paren == 0 => {
                let mut depth = 0;
                while j < toks.len() {
                    match toks[j] {
                        Tok::Punct('{') => depth += 1,
                        Tok::Punct('}') => {
                            depth -= 1;
                            if depth == 0 {
                                return j + 1;
                            }
                        }
                        _ => {}
                    }
                    j += 1;
                }
                return j;
            }
            _ => {}
        }
        j += 1;
    }
    j
}

#[cfg(test)]
mod tests {
    use super::*;

    fn idents(src: &str) -> Vec<String> {
        let (t, _) = without_test_items(&tokenize(src));
        t.into_iter()
            .filter_map(|t| match t {
                Tok::Ident(s) => Some(s),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn comments_literals_and_test_items_are_dropped() {
        let src = r##"
            // use crate::gone_a;
            /* use crate::gone_b; /* nested */ */
            fn f<'a>(x: &'a str) -> char { let _ = "crate::gone_c"; let _ = r#"crate::gone_d"#; 'x' }
            #[cfg(test)]
            mod tests { use crate::gone_e; }
            #[cfg(test)]
            use crate::gone_f;
            use crate::kept;
        "##;
        let ids = idents(src);
        assert!(!ids.iter().any(|i| i.starts_with("gone_")), "{ids:?}");
        assert!(ids.contains(&"kept".to_string()), "{ids:?}");
    }

    #[test]
    fn test_module_files_are_reported() {
        let (_, mods) = without_test_items(&tokenize("#[cfg(test)]\nmod proptests;\nmod real;"));
        assert_eq!(mods, ["proptests"]);
    }
}
