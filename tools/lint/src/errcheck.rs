//! Error types that would print their cause twice: a `thiserror` variant whose message embeds
//! a field (`{source}`, `{0}`) that is also its `source()` (`#[source]`, `#[from]`, or a field
//! named `source`). `anyhow`'s `{:#}`, which the CLI uses, prints the message and then every
//! source, so such a cause appears twice ("No such file or directory (os error 2): No such file
//! or directory (os error 2)"). The project's rule: the cause goes in the message, never in
//! `source()` (or the variant is `#[error(transparent)]`).

use std::path::{Path, PathBuf};

use crate::source::{tokenize, without_test_items, Tok};

/// A variant that repeats its cause.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Finding {
    pub file: PathBuf,
    pub variant: String,
    /// The field that is both in the message and the source.
    pub field: String,
}

impl std::fmt::Display for Finding {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}: variant `{}` puts `{}` in its message and also returns it as source(); \
             `{{:#}}` prints it twice (keep it in the message only, or use #[error(transparent)])",
            self.file.display(),
            self.variant,
            self.field
        )
    }
}

/// Checks one file's text.
pub fn check_text(file: &Path, text: &str) -> Vec<Finding> {
    let (t, _) = without_test_items(&tokenize(text));
    let mut out = Vec::new();
    let mut i = 0;
    while i + 3 < t.len() {
        let is_error_attr = t[i] == Tok::Punct('#')
            && t[i + 1] == Tok::Punct('[')
            && t[i + 2] == Tok::Ident("error".into())
            && t[i + 3] == Tok::Punct('(');
        if !is_error_attr {
            i += 1;
            continue;
        }
        // The attribute's tokens up to its closing `]`.
        let mut j = i + 1;
        let mut depth = 0;
        let attr_start = i + 4;
        while j < t.len() {
            match t[j] {
                Tok::Punct('[') => depth += 1,
                Tok::Punct(']') => {
                    depth -= 1;
                    if depth == 0 {
                        break;
                    }
                }
                _ => {}
            }
            j += 1;
        }
        let attr = &t[attr_start..j.min(t.len())];
        i = j + 1;
        if attr.first() == Some(&Tok::Ident("transparent".into())) {
            continue;
        }
        let message = match attr.first() {
            Some(Tok::Str(s)) => s.clone(),
            _ => String::new(),
        };
        // Further attributes on the variant.
        while t.get(i) == Some(&Tok::Punct('#')) {
            let mut d = 0;
            while i < t.len() {
                match t[i] {
                    Tok::Punct('[') => d += 1,
                    Tok::Punct(']') => {
                        d -= 1;
                        if d == 0 {
                            i += 1;
                            break;
                        }
                    }
                    _ => {}
                }
                i += 1;
            }
        }
        let Some(Tok::Ident(variant)) = t.get(i) else {
            continue;
        };
        let (open, close) = match t.get(i + 1) {
            Some(Tok::Punct('(')) => ('(', ')'),
            Some(Tok::Punct('{')) => ('{', '}'),
            _ => continue,
        };
        // Fields, split at top-level commas.
        let mut k = i + 2;
        let mut depth = 1;
        let mut fields: Vec<Vec<Tok>> = vec![Vec::new()];
        while k < t.len() {
            let tok = &t[k];
            match tok {
                Tok::Punct(c) if *c == open || *c == '<' || *c == '(' || *c == '{' => depth += 1,
                Tok::Punct(c) if *c == close || *c == '>' || *c == ')' || *c == '}' => {
                    depth -= 1;
                    if depth == 0 {
                        break;
                    }
                }
                Tok::Punct(',') if depth == 1 => {
                    fields.push(Vec::new());
                    k += 1;
                    continue;
                }
                _ => {}
            }
            if let Some(f) = fields.last_mut() {
                f.push(tok.clone());
            }
            k += 1;
        }
        for (pos, field) in fields.iter().enumerate() {
            if field.is_empty() {
                continue;
            }
            let has_attr = |name: &str| {
                field.windows(3).any(|w| {
                    w[0] == Tok::Punct('#')
                        && w[1] == Tok::Punct('[')
                        && w[2] == Tok::Ident(name.into())
                })
            };
            // The field's name: the identifier before its `:` (named fields), else its index.
            let name = if open == '{' {
                let colon = field.iter().position(|x| *x == Tok::Punct(':'));
                match colon.and_then(|c| c.checked_sub(1)).map(|c| &field[c]) {
                    Some(Tok::Ident(n)) => n.clone(),
                    _ => continue,
                }
            } else {
                pos.to_string()
            };
            let is_source = has_attr("source") || has_attr("from") || name == "source";
            if !is_source {
                continue;
            }
            let in_message = message.contains(&format!("{{{name}}}"))
                || message.contains(&format!("{{{name}:"))
                || attr[1..].iter().any(|x| *x == Tok::Ident(name.clone()));
            if in_message {
                out.push(Finding {
                    file: file.to_path_buf(),
                    variant: variant.clone(),
                    field: name,
                });
            }
        }
        i = k;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(text: &str) -> Vec<String> {
        check_text(Path::new("x.rs"), text)
            .into_iter()
            .map(|f| format!("{}.{}", f.variant, f.field))
            .collect()
    }

    #[test]
    fn repeated_causes_are_found_and_the_rule_is_accepted() {
        let text = r#"
            #[derive(Debug, thiserror::Error)]
            enum E {
                #[error("{path}: {source}")]
                Named { path: String, source: std::io::Error },
                #[error("{0}")]
                From(#[from] std::io::Error),
                #[error("reading {}: {}", .path.display(), .err)]
                Marked { path: PathBuf, #[source] err: std::io::Error },
                #[error("{path}: {err}")]
                Fine { path: String, err: std::io::Error },
                #[error("cannot read {path}")]
                ChainOnly { path: String, #[source] err: std::io::Error },
                #[error(transparent)]
                Wrapped(#[from] std::fmt::Error),
                #[error("bad {0}: {1}")]
                Plain(String, String),
            }
        "#;
        assert_eq!(names(text), ["Named.source", "From.0", "Marked.err"]);
    }
}
