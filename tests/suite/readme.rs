//! The README's newcomer path, run as written (issue 33, "First contact"): every shell block
//! whose info string is `sh omnid-test`, in order, in one temporary directory that stands for
//! a fresh clone (its `clients/` is the repository's), with a private runtime directory (the
//! daemon's socket) and state directory (motor heat, fault dumps), and `omnid` on `PATH` as
//! the binary under test. The README's development section describes the marker.
//!
//! In such a block a command is a line (with `\` continuations and `<<'EOF'` here-documents);
//! the lines `#> TEXT` after it are what it prints (stdout and stderr together): each must be
//! found in one line of its output, `…` standing for any text. A command ending in `&` runs in
//! the background: it has started when its first shown line appears, and it is stopped at the
//! end (SIGTERM) unless it ended by itself; its lines are checked then. `wait` waits, as the
//! shell's does, for the background commands to end; the lines shown after it are looked for
//! in what they printed. Every foreground command must exit 0 within its time limit, a
//! background one with 0 (or 130, stopped here), and a background command that reports a
//! safety trip (the daemon) fails the walk-through.

use std::io::Read;
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The info string that marks a README block as part of the tested walk-through.
const MARKER: &str = "sh omnid-test";
/// The longest any one command may take.
const COMMAND_LIMIT: Duration = Duration::from_secs(60);
/// How long a background command may take to print its first shown line, and to end after
/// the walk-through.
const BACKGROUND_LIMIT: Duration = Duration::from_secs(30);

/// One command of the walk-through.
#[derive(Debug)]
struct Step {
    /// Line in the README where it starts.
    line: usize,
    /// The command as the shell is given it (without a trailing `&`).
    command: String,
    background: bool,
    /// The lines shown as its output (`#> `), in order.
    shown: Vec<String>,
}

/// The start of a here-document's delimiter in `line` (`<<'EOF'`, `<<"EOF"`, `<<EOF`): EOF.
fn heredoc_end(line: &str) -> Option<String> {
    let at = line.find("<<")?;
    let rest = line[at + 2..].trim_start_matches('-').trim_start();
    let word: String = rest
        .trim_start_matches(['\'', '"'])
        .chars()
        .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
        .collect();
    (!word.is_empty()).then_some(word)
}

/// A command line's text before its trailing comment (` #` outside quotes, simply: the
/// first ` #`), trimmed.
fn without_comment(line: &str) -> &str {
    line.find(" #").map_or(line, |i| &line[..i]).trim_end()
}

/// The walk-through's steps, in the README's order.
fn steps(readme: &str) -> Result<Vec<Step>, String> {
    let mut steps: Vec<Step> = Vec::new();
    let mut lines = readme.lines().enumerate().map(|(i, l)| (i + 1, l));
    while let Some((_, line)) = lines.next() {
        if line.trim() != format!("```{MARKER}") {
            continue;
        }
        let mut closed = false;
        while let Some((n, line)) = lines.next() {
            if line.trim_start().starts_with("```") {
                closed = true;
                break;
            }
            if let Some(text) = line.strip_prefix("#>") {
                let text = text.strip_prefix(' ').unwrap_or(text);
                match steps.last_mut() {
                    Some(step) => step.shown.push(text.to_string()),
                    None => return Err(format!("README.md:{n}: `#>` before any command")),
                }
                continue;
            }
            if line.trim().is_empty() || line.trim_start().starts_with('#') {
                continue;
            }
            let mut command = line.to_string();
            let mut last = line.to_string();
            while last.ends_with('\\') {
                let Some((_, next)) = lines.next() else { break };
                command = format!("{}\n{next}", command);
                last = next.to_string();
            }
            if let Some(end) = heredoc_end(&command) {
                loop {
                    let Some((_, next)) = lines.next() else {
                        return Err(format!("README.md:{n}: here-document never ends ({end})"));
                    };
                    command = format!("{command}\n{next}");
                    if next.trim_end() == end {
                        break;
                    }
                }
            }
            let head = without_comment(command.lines().next().unwrap_or_default());
            let background = head.ends_with('&') && !head.ends_with("&&");
            if background {
                command = head.trim_end_matches('&').trim_end().to_string();
            }
            steps.push(Step {
                line: n,
                command,
                background,
                shown: Vec::new(),
            });
        }
        if !closed {
            return Err("README.md: a walk-through block is never closed".into());
        }
    }
    Ok(steps)
}

/// `text` with every run of white space made one space, trimmed.
fn squeeze(text: &str) -> String {
    text.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// `shown` (with `…` for any text) is in one line of `output`; white space counts as one
/// space wherever it is (the README lines up its columns by hand).
fn shows(output: &str, shown: &str) -> bool {
    let parts: Vec<String> = shown.split('…').map(squeeze).collect();
    output.lines().any(|line| {
        let line = squeeze(line);
        let mut rest = line.as_str();
        parts.iter().all(|p| match rest.find(p.as_str()) {
            Some(i) => {
                rest = &rest[i + p.len()..];
                true
            }
            None => false,
        })
    })
}

/// Every shown line of `step` in `output`, or which is not (with the output).
fn check_shown(step: &Step, output: &str) -> Result<(), String> {
    match step.shown.iter().find(|s| !shows(output, s)) {
        None => Ok(()),
        Some(missing) => Err(format!(
            "README.md:{}: `{}` did not print\n    {missing}\nit printed:\n{output}",
            step.line, step.command
        )),
    }
}

/// A process group started for a step: killed (the whole group) if the walk-through fails.
struct Running {
    child: Child,
    out: PathBuf,
}

impl Running {
    fn output(&self) -> String {
        let mut s = String::new();
        if let Ok(mut f) = std::fs::File::open(&self.out) {
            let _ = f.read_to_string(&mut s);
        }
        s
    }

    fn signal(&self, sig: i32) {
        // SAFETY: a signal to the process group of our own child (its pid is the group's id,
        // `process_group(0)`); the child is not reaped before this struct drops.
        unsafe { libc::kill(-(self.child.id() as i32), sig) };
    }

    /// Its exit status once it ends, or None at `until`.
    fn wait_until(&mut self, until: Instant) -> Option<std::process::ExitStatus> {
        loop {
            if let Some(status) = self.child.try_wait().expect("waits") {
                return Some(status);
            }
            if Instant::now() >= until {
                return None;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        if self.child.try_wait().ok().flatten().is_none() {
            self.signal(libc::SIGKILL);
            let _ = self.child.wait();
        }
    }
}

/// A fresh clone's stand-in: the working directory (with the repository's `clients/`), the
/// runtime and state directories, and a directory with `omnid` for `PATH`.
struct Clone {
    dir: tempfile::TempDir,
}

impl Clone {
    fn new() -> Clone {
        let dir = tempfile::tempdir().unwrap();
        let root = Path::new(env!("CARGO_MANIFEST_DIR"));
        for d in ["clone", "run", "state", "bin"] {
            std::fs::create_dir(dir.path().join(d)).unwrap();
        }
        std::os::unix::fs::symlink(root.join("clients"), dir.path().join("clone/clients")).unwrap();
        std::os::unix::fs::symlink(env!("CARGO_BIN_EXE_omnid"), dir.path().join("bin/omnid"))
            .unwrap();
        Clone { dir }
    }

    fn start(&self, step: &Step, n: usize) -> Running {
        let out = self.dir.path().join(format!("step-{n}.out"));
        let file = std::fs::File::create(&out).unwrap();
        let path = format!(
            "{}:{}",
            self.dir.path().join("bin").display(),
            std::env::var("PATH").unwrap_or_default()
        );
        let child = Command::new("sh")
            .arg("-c")
            .arg(&step.command)
            .current_dir(self.dir.path().join("clone"))
            .env("PATH", path)
            .env("XDG_RUNTIME_DIR", self.dir.path().join("run"))
            .env("OMNID_STATE_DIR", self.dir.path().join("state"))
            .env("PYTHONDONTWRITEBYTECODE", "1")
            .env_remove("RUNTIME_DIRECTORY")
            .env_remove("OMNID_SOCKET")
            .env_remove("PYTHONPATH")
            .stdin(Stdio::null())
            .stdout(file.try_clone().unwrap())
            .stderr(file)
            .process_group(0)
            .spawn()
            .expect("sh starts");
        Running { child, out }
    }
}

/// A line of a daemon's output that says the safety layer tripped (the station's
/// `omnid serve: ARM: safety: …` line, or a run ended by a safety fault).
fn trip_line(output: &str) -> Option<&str> {
    output
        .lines()
        .find(|l| l.contains(": safety: ") || l.contains("safety fault"))
}

/// End the background commands: each must end by itself within `BACKGROUND_LIMIT` (`wait`),
/// or is stopped with SIGTERM (`stop`, the walk-through's end). Each must end with 0 (or 130
/// when stopped here), without a safety trip, having printed its own shown lines. Returns
/// their outputs, together.
fn end_background(background: Vec<(&Step, Running)>, stop: bool) -> Result<String, String> {
    let mut all = String::new();
    for (step, mut running) in background {
        let limit = if stop {
            Duration::ZERO
        } else {
            BACKGROUND_LIMIT
        };
        let status = match running.wait_until(Instant::now() + limit) {
            Some(status) => status,
            None if stop => {
                running.signal(libc::SIGTERM);
                running
                    .wait_until(Instant::now() + BACKGROUND_LIMIT)
                    .ok_or_else(|| {
                        format!(
                            "README.md:{}: `{}` did not stop within {BACKGROUND_LIMIT:?} of \
                             SIGTERM",
                            step.line, step.command
                        )
                    })?
            }
            None => {
                return Err(format!(
                    "README.md:{}: `{}` did not end within {BACKGROUND_LIMIT:?} of `wait`; it \
                     printed:\n{}",
                    step.line,
                    step.command,
                    running.output()
                ))
            }
        };
        let output = running.output();
        let stopped_here = stop && (status.code() == Some(130) || status.signal() == Some(15));
        if !(status.success() || stopped_here) {
            return Err(format!(
                "README.md:{}: `{}` ended with {status}; it printed:\n{output}",
                step.line, step.command
            ));
        }
        if let Some(trip) = trip_line(&output) {
            return Err(format!(
                "README.md:{}: `{}` tripped the safety layer during the walk-through:\n    \
                 {trip}\nit printed:\n{output}",
                step.line, step.command
            ));
        }
        check_shown(step, &output)?;
        all += &output;
    }
    Ok(all)
}

/// Every file under `dir` (symbolic links not followed), as paths relative to `root`.
fn files_under(root: &Path, dir: &Path, out: &mut Vec<String>) {
    for entry in std::fs::read_dir(dir).unwrap().map(Result::unwrap) {
        let path = entry.path();
        if entry.file_type().unwrap().is_dir() {
            files_under(root, &path, out);
        } else {
            out.push(path.strip_prefix(root).unwrap().display().to_string());
        }
    }
}

/// Run the walk-through of `readme`: the number of commands run and the files it left in the
/// clone (paths in it; the repository's own `clients/` aside), or what went wrong where.
fn walk(readme: &str) -> Result<(usize, Vec<String>), String> {
    let steps = steps(readme)?;
    if steps.is_empty() {
        return Err(format!("README.md has no block marked ```{MARKER}"));
    }
    let clone = Clone::new();
    let mut background: Vec<(&Step, Running)> = Vec::new();
    for (n, step) in steps.iter().enumerate() {
        if step.command.trim() == "wait" {
            // The shell's `wait`: the background commands end; what they printed is shown.
            let output = end_background(std::mem::take(&mut background), false)?;
            check_shown(step, &output)?;
            continue;
        }
        let mut running = clone.start(step, n);
        if step.background {
            // Started when its first shown line appears (it may not end first).
            let until = Instant::now() + BACKGROUND_LIMIT;
            if let Some(first) = step.shown.first() {
                while !shows(&running.output(), first) {
                    if let Some(status) = running.child.try_wait().expect("waits") {
                        return Err(format!(
                            "README.md:{}: `{}` ended ({status}) before printing\n    {first}\n\
                             it printed:\n{}",
                            step.line,
                            step.command,
                            running.output()
                        ));
                    }
                    if Instant::now() >= until {
                        return Err(format!(
                            "README.md:{}: `{}` did not print `{first}` within {:?}; it \
                             printed:\n{}",
                            step.line,
                            step.command,
                            BACKGROUND_LIMIT,
                            running.output()
                        ));
                    }
                    std::thread::sleep(Duration::from_millis(20));
                }
            }
            background.push((step, running));
            continue;
        }
        let Some(status) = running.wait_until(Instant::now() + COMMAND_LIMIT) else {
            return Err(format!(
                "README.md:{}: `{}` did not end within {COMMAND_LIMIT:?}; it printed:\n{}",
                step.line,
                step.command,
                running.output()
            ));
        };
        let output = running.output();
        if !status.success() {
            return Err(format!(
                "README.md:{}: `{}` failed ({status}); it printed:\n{output}",
                step.line, step.command
            ));
        }
        check_shown(step, &output)?;
    }
    end_background(background, true)?;
    let root = clone.dir.path().join("clone");
    let mut written = Vec::new();
    files_under(&root, &root, &mut written);
    written.retain(|f| f != "clients");
    Ok((steps.len(), written))
}

#[test]
#[ignore = "paced"]
fn the_readme_walk_through_runs_as_written_and_prints_what_it_shows() {
    let readme =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("README.md")).unwrap();
    let (n, written) = walk(&readme).unwrap_or_else(|e| panic!("{e}"));
    assert!(n >= 10, "only {n} commands in the walk-through");
    // What it writes does not land untracked in the clone: git ignores every file of it.
    assert!(
        written.iter().any(|f| f.ends_with("track.csv")),
        "the recording is among the files: {written:?}"
    );
    for file in &written {
        let ignored = Command::new("git")
            .args(["check-ignore", "--no-index", "-q", file])
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .status()
            .expect("git runs");
        assert!(
            ignored.success(),
            "the walk-through leaves `{file}` untracked in the clone (not in .gitignore)"
        );
    }
}

/// The runner itself: a wrong command, a line the command does not print, and a daemon left
/// running each fail (or are stopped) as the README's would.
#[test]
#[ignore = "paced"]
fn a_wrong_command_or_a_drifted_output_fails_the_walk_through() {
    let block = |body: &str| format!("text\n\n```{MARKER}\n{body}\n```\n");
    let wrong = walk(&block("omnid ctl mode hodl")).unwrap_err();
    assert!(
        wrong.contains("omnid ctl mode hodl") && wrong.contains("failed"),
        "{wrong}"
    );

    let drifted = walk(&block(
        "omnid config --print-default\n#> [safety]\n#> [no-such-section]",
    ))
    .unwrap_err();
    assert!(drifted.contains("    [no-such-section]"), "{drifted}");

    let shown = walk(&block(
        "omnid config --print-default   # every key\n#> [safety]\n#> max_torque_nm = …]",
    ));
    assert_eq!(shown.map(|w| w.0), Ok(1));

    let never_prints = walk(&block("true &\n#> ready")).unwrap_err();
    assert!(never_prints.contains("before printing"), "{never_prints}");

    // Never ends by itself: stopped at the end, and its shown lines were printed.
    let endless = "sh -c 'echo ready; sleep 100' &\n#> ready\necho\n";
    assert_eq!(walk(&block(endless)).map(|w| w.0), Ok(2));
    // `wait` for one that ends, and what it printed is looked for.
    let background = "sh -c 'echo ready; echo done' &\n#> ready\necho\n";
    assert_eq!(
        walk(&block(&format!("{background}wait\n#> done"))).map(|w| w.0),
        Ok(3)
    );
    let not_done = walk(&block(&format!("{background}wait\n#> finished"))).unwrap_err();
    assert!(not_done.contains("    finished"), "{not_done}");

    let failed = walk(&block("sh -c 'echo ready; exit 3' &\n#> ready\nwait")).unwrap_err();
    assert!(failed.contains("ended with"), "{failed}");
    let tripped = walk(&block(
        "sh -c 'echo ready; echo omnid serve: sim: safety: joint 2 too fast' &\n#> ready\nwait",
    ))
    .unwrap_err();
    assert!(tripped.contains("tripped the safety layer"), "{tripped}");
}

#[test]
#[ignore = "paced"]
fn commands_continuations_heredocs_and_background_are_read_as_the_shell_reads_them() {
    let md = format!(
        "```sh\nnot this\n```\n```{MARKER}\n# a comment\nomnid serve &   # the daemon\n#> on …sock\n\
         python3 - <<'EOF'\nprint(1)\nEOF\n#> 1\nomnid run \\\n  --fast\n```\n"
    );
    let s = steps(&md).unwrap();
    assert_eq!(s.len(), 3, "{s:?}");
    assert!(s[0].background && s[0].command == "omnid serve", "{s:?}");
    assert_eq!(s[0].shown, ["on …sock"]);
    assert_eq!(s[1].command, "python3 - <<'EOF'\nprint(1)\nEOF");
    assert_eq!(s[1].shown, ["1"]);
    assert_eq!(s[2].command, "omnid run \\\n  --fast");
    assert!(!s[2].background);
    assert!(shows("a x b y c", "a … b … c"));
    assert!(!shows("a x c\nb", "a … b"));
}
