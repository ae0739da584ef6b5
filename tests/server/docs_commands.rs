//! Every `mpiflow` command the user's documents show (README.md and docs/*.md: the lines of code
//! blocks and the inline code spans that run `mpiflow`, `target/release/mpiflow` or
//! `cargo run --release -- ...`) names subcommands that exist and only flags that the
//! subcommand's `--help` lists. Runs the real binary's help, so a renamed or removed flag fails
//! here until the documents follow.

use std::collections::HashMap;
use std::path::Path;
use std::process::Command;

/// One documented command: where it is, and its words after `mpiflow`.
#[derive(Debug)]
struct Documented {
    at: String,
    words: Vec<String>,
}

/// The words after `mpiflow` when `line` runs it (a shell prompt `$ `, `VAR=value` assignments and
/// a path before the binary allowed; `cargo run ... -- ARGS` runs it too), up to the first shell
/// operator or comment.
fn command_words(line: &str) -> Option<Vec<String>> {
    let mut words = line.split_whitespace().peekable();
    if words.peek() == Some(&"$") {
        words.next();
    }
    while words.peek().is_some_and(|w| {
        w.split_once('=').is_some_and(|(k, _)| !k.is_empty() && k.chars().all(|c| c.is_ascii_uppercase() || c == '_'))
    }) {
        words.next();
    }
    let first = words.next()?;
    if first == "cargo" {
        if words.next() != Some("run") {
            return None;
        }
        words.by_ref().find(|w| *w == "--")?;
    } else if first != "mpiflow" && !first.ends_with("/mpiflow") {
        return None;
    }
    let mut out = Vec::new();
    for w in words {
        if matches!(w, "|" | "||" | "&&" | "&" | ";" | ">" | ">>" | "2>&1" | "<") || w.starts_with('#') {
            break;
        }
        out.push(w.to_string());
    }
    Some(out)
}

/// The subcommands of `mpiflow` (the check below holds them to the binary's help).
const TOP_COMMANDS: [&str; 8] = ["bake", "render", "bench", "generate", "serve", "pull", "health", "models"];

/// The commands of a markdown text: each line of a fenced code block (a line ending in `\` goes
/// on in the next one) and each inline code span (which may run over line breaks).
fn documented(name: &str, text: &str) -> Vec<Documented> {
    let mut out = Vec::new();
    let mut in_block = false;
    let mut pending = String::new();
    let mut prose = String::new();
    let mut prose_line = 1;
    let flush_prose = |prose: &mut String, first_line: usize, out: &mut Vec<Documented>| {
        for (k, span) in prose.split('`').enumerate() {
            if k % 2 == 1 {
                let span = span.split_whitespace().collect::<Vec<_>>().join(" ");
                // prose quotes the server's own lines too (`mpiflow serving on HOST:PORT`): a span
                // is a command when a subcommand or a flag follows `mpiflow`
                let command = command_words(&span)
                    .filter(|w| w.first().is_some_and(|w| w.starts_with('-') || TOP_COMMANDS.contains(&w.as_str())));
                if let Some(words) = command {
                    out.push(Documented { at: format!("{name} (paragraph at line {first_line})"), words });
                }
            }
        }
        prose.clear();
    };
    for (i, line) in text.lines().enumerate() {
        let n = i + 1;
        if line.trim_start().starts_with("```") {
            in_block = !in_block;
            pending.clear();
            flush_prose(&mut prose, prose_line, &mut out);
            continue;
        }
        if in_block {
            let (body, goes_on) = match line.trim_end().strip_suffix('\\') {
                Some(b) => (b, true),
                None => (line, false),
            };
            pending.push_str(body);
            pending.push(' ');
            if !goes_on {
                if let Some(words) = command_words(&pending) {
                    out.push(Documented { at: format!("{name}:{n}"), words });
                }
                pending.clear();
            }
        } else if line.trim().is_empty() {
            flush_prose(&mut prose, prose_line, &mut out);
        } else {
            if prose.is_empty() {
                prose_line = n;
            }
            prose.push_str(line);
            prose.push('\n');
        }
    }
    flush_prose(&mut prose, prose_line, &mut out);
    out
}

/// What `mpiflow PATH --help` lists: its subcommands and its `--flags`.
#[derive(Debug, Default)]
struct Help {
    commands: Vec<String>,
    flags: Vec<String>,
}

fn parse_help(text: &str) -> Help {
    let mut help = Help::default();
    let mut in_commands = false;
    for line in text.lines() {
        if line.trim_end() == "Commands:" {
            in_commands = true;
            continue;
        }
        if line.trim().is_empty() || !line.starts_with(' ') {
            in_commands = false;
        }
        let trimmed = line.trim_start();
        if in_commands && line.starts_with("  ") && !line.starts_with("   ") {
            if let Some(name) = trimmed.split_whitespace().next() {
                help.commands.push(name.to_string());
            }
        }
        if trimmed.starts_with('-') {
            let flag = trimmed
                .split(|c: char| c.is_whitespace() || c == ',' || c == '=' || c == '<' || c == '[')
                .find(|w| w.starts_with("--"));
            if let Some(f) = flag {
                help.flags.push(f.to_string());
            }
        }
        // aliases clap shows beside a flag or a command
        if let Some(i) = line.find("[aliases: ") {
            let list = &line[i + 10..line[i..].find(']').map_or(line.len(), |j| i + j)];
            for a in list.split(',').map(str::trim) {
                if a.starts_with("--") {
                    help.flags.push(a.to_string());
                } else if in_commands {
                    help.commands.push(a.to_string());
                }
            }
        }
    }
    help
}

/// The help of `mpiflow PATH`, run once per path.
fn help_of<'a>(cache: &'a mut HashMap<Vec<String>, Help>, path: &[String]) -> &'a Help {
    cache.entry(path.to_vec()).or_insert_with(|| {
        let out = Command::new(env!("CARGO_BIN_EXE_mpiflow")).args(path).arg("--help").output().unwrap();
        assert!(
            out.status.success(),
            "mpiflow {} --help failed: {}",
            path.join(" "),
            String::from_utf8_lossy(&out.stderr)
        );
        parse_help(&String::from_utf8_lossy(&out.stdout))
    })
}

/// The faults of one documented command against the binary's help.
fn check(cache: &mut HashMap<Vec<String>, Help>, doc: &Documented) -> Vec<String> {
    let mut faults = Vec::new();
    let mut path: Vec<String> = Vec::new();
    let mut words = doc.words.iter().map(|w| w.trim_matches(|c: char| "[]()'\"".contains(c))).filter(|w| !w.is_empty());
    let mut rest = Vec::new();
    // the subcommands: while the command at `path` has subcommands, the next word names one
    loop {
        let help = help_of(cache, &path);
        if help.commands.is_empty() {
            break;
        }
        match words.next() {
            Some(w) if w.starts_with('-') => {
                rest.push(w);
                break;
            }
            Some(w) if help.commands.iter().any(|c| c == w) => path.push(w.to_string()),
            Some(w) => {
                faults.push(format!(
                    "{}: `mpiflow {}` has no subcommand `{w}` (it has {})",
                    doc.at,
                    path.join(" "),
                    help.commands.join(", ")
                ));
                return faults;
            }
            None => break,
        }
    }
    rest.extend(words);
    let help = help_of(cache, &path);
    // after a bare `--`, the words go to another program (`bench soak -- SERVE FLAGS`)
    for w in rest.into_iter().take_while(|w| *w != "--") {
        let Some(flag) = w.strip_prefix("--").map(|f| f.split('=').next().unwrap_or(f)) else { continue };
        if flag.is_empty() || flag.contains("...") {
            continue;
        }
        let flag = format!("--{flag}");
        if !help.flags.contains(&flag) {
            faults.push(format!("{}: `mpiflow {}` has no flag `{flag}`", doc.at, path.join(" ")));
        }
    }
    faults
}

#[test]
fn every_documented_command_matches_the_binary() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = vec![root.join("README.md")];
    let mut docs: Vec<_> = std::fs::read_dir(root.join("docs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "md"))
        .collect();
    docs.sort();
    files.extend(docs);
    let mut cache = HashMap::new();
    let mut faults = Vec::new();
    let mut commands = 0;
    for f in &files {
        let name = f.strip_prefix(root).unwrap().to_string_lossy().to_string();
        for doc in documented(&name, &std::fs::read_to_string(f).unwrap()) {
            commands += 1;
            faults.extend(check(&mut cache, &doc));
        }
    }
    assert!(commands > 50, "found only {commands} documented commands");
    assert!(faults.is_empty(), "documented commands the binary does not take:\n{}", faults.join("\n"));
}

#[test]
fn the_subcommands_listed_here_are_the_binarys() {
    let mut cache = HashMap::new();
    let mut listed = help_of(&mut cache, &[]).commands.clone();
    listed.retain(|c| c != "help");
    assert_eq!(listed, TOP_COMMANDS);
}

#[test]
fn the_scanner_finds_commands_and_the_checker_faults() {
    assert_eq!(
        command_words("$ MPIFLOW_X=1 target/release/mpiflow serve --addr a:1 | tee x").unwrap(),
        ["serve", "--addr", "a:1"]
    );
    assert_eq!(
        command_words("cargo run --release --features plots -- bench accuracy --out x").unwrap(),
        ["bench", "accuracy", "--out", "x"]
    );
    assert!(command_words("docker run -d --name mpiflow mpiflow:latest").is_none());
    assert!(command_words("from mpiflow import Client").is_none());
    let text = "Run `mpiflow generate --count 4\n--no-such-flag` here; it says `mpiflow serving on x`.\n\n```sh\nmpiflow bench quality \\\n  --background planes\nmpiflow frobnicate\n```\n";
    let docs = documented("x.md", text);
    assert_eq!(docs.len(), 3, "{docs:?}");
    let mut cache = HashMap::new();
    let faults: Vec<String> = docs.iter().flat_map(|d| check(&mut cache, d)).collect();
    assert_eq!(faults.len(), 3, "{faults:?}");
    assert!(faults[0].contains("`mpiflow generate` has no flag `--no-such-flag`"), "{faults:?}");
    assert!(faults[1].contains("x.md:6: `mpiflow bench quality` has no flag `--background`"), "{faults:?}");
    assert!(faults[2].contains("no subcommand `frobnicate`"), "{faults:?}");
}
