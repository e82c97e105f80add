//! Data-parallel training under a real `mpirun` (the `mpi` feature; CI installs Open MPI and
//! runs these): two ranks train the same model one process trains with `accumulate = 2`, a
//! resumed run may change the rank count, diverged weights are caught, a rank that dies ends
//! the job instead of leaving the other waiting, SIGUSR1 to `mpirun` stops every rank after the
//! same step with a checkpoint, and two ranks on two "machines" (network namespaces joined by a
//! virtual Ethernet link) train over Open MPI's TCP transport.

#![cfg(feature = "mpi")]

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::{Device, Tensor};
use lifegom_model::trained;

/// The tiny split and a copy of its config with `extra` appended to `[train]`.
struct Setup {
    tmp: PathBuf,
    data: PathBuf,
}

impl Setup {
    fn new(tag: &str) -> Self {
        let (tmp, cfg) = common::tiny_split(tag, |_| {});
        Self {
            data: cfg.data.root.clone(),
            tmp,
        }
    }

    /// `configs/synthetic-tiny.toml` with `extra` lines added to its `[train]` section.
    fn config(&self, name: &str, extra: &str) -> PathBuf {
        let base = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs/synthetic-tiny.toml");
        let text = std::fs::read_to_string(base).expect("reading the tiny config");
        let text = text.replacen("[train]\n", &format!("[train]\n{extra}\n"), 1);
        let path = self.tmp.join(format!("{name}.toml"));
        std::fs::write(&path, text).expect("writing a test config");
        path
    }

    /// [`Setup::command`] without a fault, run to its end; fails the test unless it succeeds.
    fn train_ok(&self, config: &Path, out: &Path, steps: u64, launch: &Launch, resume: bool) {
        succeeded(&finish(
            self.command(config, out, steps, launch, resume, None),
        ));
    }

    /// `lifegom-train` on `config` for `steps` steps into `out`, started as `launch` says; the
    /// environment's `LIFEGOM_MPI_FAULT` is `fault`.
    fn command(
        &self,
        config: &Path,
        out: &Path,
        steps: u64,
        launch: &Launch,
        resume: bool,
        fault: Option<&str>,
    ) -> Command {
        let exe = env!("CARGO_BIN_EXE_lifegom-train");
        let mut cmd = match launch {
            Launch::Alone => Command::new(exe),
            Launch::Local(ranks) => {
                let mut c = Command::new("mpirun");
                // Root in CI containers; two ranks on a 2-core machine; no shared-memory
                // single-copy (CMA is not permitted in many containers).
                c.args(["--allow-run-as-root", "--oversubscribe", "-np"])
                    .arg(ranks.to_string())
                    .args(["--mca", "btl_vader_single_copy_mechanism", "none"])
                    .arg(exe);
                c
            }
            Launch::Network(net) => net.mpirun(exe),
        };
        cmd.arg("--config")
            .arg(config)
            .args(["--device", "ndarray", "--steps"])
            .arg(steps.to_string())
            .arg("--data")
            .arg(&self.data)
            .arg("--out")
            .arg(out)
            .env("RAYON_NUM_THREADS", "1")
            .env_remove("LIFEGOM_MPI_FAULT")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        if let Some(f) = fault {
            cmd.env("LIFEGOM_MPI_FAULT", f);
        }
        if resume {
            cmd.arg("--resume");
        }
        cmd
    }
}

/// How the training processes are started.
enum Launch<'a> {
    /// One process, no launcher.
    Alone,
    /// `mpirun -np N` on this machine.
    Local(usize),
    /// Two ranks in two network namespaces.
    Network(&'a TwoHosts),
}

/// Two network namespaces ("hosts") joined by a veth pair named `mpi0` on both ends, with
/// loopback-range addresses 127.0.77.1 and 127.0.77.2 (routed off `lo` by `route_localnet`,
/// `lo` keeping only 127.0.0.1/32). `mpirun` runs in the first; it starts the second rank's
/// daemon through an "rsh agent" script that enters the second namespace instead of ssh-ing
/// to a machine. Removed on drop.
struct TwoHosts {
    names: [String; 2],
    agent: PathBuf,
}

const HOST_ADDRESSES: [&str; 2] = ["127.0.77.1", "127.0.77.2"];

impl TwoHosts {
    fn new(dir: &Path) -> Self {
        let pid = std::process::id();
        let names = [format!("lgmpi{pid}a"), format!("lgmpi{pid}b")];
        let hosts = Self {
            agent: dir.join("netns-agent.sh"),
            names,
        };
        let [a, b] = &hosts.names;
        let (va, vb) = (format!("lgv{pid}a"), format!("lgv{pid}b"));
        ip(&["netns", "add", a]);
        ip(&["netns", "add", b]);
        ip(&["link", "add", &va, "type", "veth", "peer", "name", &vb]);
        for (ns, veth, address) in [(a, &va, HOST_ADDRESSES[0]), (b, &vb, HOST_ADDRESSES[1])] {
            ip(&["link", "set", veth, "netns", ns]);
            let inside = |args: &[&str]| {
                let mut all = vec!["netns", "exec", ns.as_str()];
                all.extend_from_slice(args);
                ip(&all);
            };
            inside(&["ip", "link", "set", "lo", "up"]);
            inside(&["ip", "addr", "del", "127.0.0.1/8", "dev", "lo"]);
            inside(&["ip", "addr", "add", "127.0.0.1/32", "dev", "lo"]);
            inside(&["ip", "link", "set", veth, "name", "mpi0"]);
            inside(&["ip", "addr", "add", &format!("{address}/24"), "dev", "mpi0"]);
            // `route_localnet` through /proc (per namespace), without procps' sysctl.
            for conf in ["all", "mpi0"] {
                let knob = format!("echo 1 > /proc/sys/net/ipv4/conf/{conf}/route_localnet");
                inside(&["sh", "-c", &knob]);
            }
            inside(&["ip", "link", "set", "mpi0", "up"]);
        }
        let script = format!(
            "#!/bin/sh\n# Open MPI's rsh agent for the test hosts: `agent HOST COMMAND…`.\n\
             host=\"$1\"; shift\n\
             case \"$host\" in\n  {}) ns={a} ;;\n  {}) ns={b} ;;\n  *) echo \"unknown host $host\" >&2; exit 1 ;;\nesac\n\
             exec ip netns exec \"$ns\" /bin/sh -c \"$*\"\n",
            HOST_ADDRESSES[0], HOST_ADDRESSES[1]
        );
        std::fs::write(&hosts.agent, script).expect("writing the rsh agent");
        let status = Command::new("chmod")
            .arg("+x")
            .arg(&hosts.agent)
            .status()
            .expect("chmod");
        assert!(status.success());
        hosts
    }

    /// `mpirun` in the first namespace, one rank on each host, over TCP on `mpi0` only (no
    /// shared memory: `btl` is `tcp,self`).
    fn mpirun(&self, exe: &str) -> Command {
        let mut c = Command::new("ip");
        c.args([
            "netns",
            "exec",
            &self.names[0],
            "mpirun",
            "--allow-run-as-root",
            "-np",
            "2",
        ])
        .arg("--host")
        .arg(format!("{}:1,{}:1", HOST_ADDRESSES[0], HOST_ADDRESSES[1]))
        .arg("--mca")
        .arg("plm_rsh_agent")
        .arg(&self.agent)
        .args(["--mca", "btl", "tcp,self"])
        .args(["--mca", "btl_tcp_if_include", "mpi0"])
        .args(["--mca", "oob_tcp_if_include", "mpi0"])
        .args(["-x", "RAYON_NUM_THREADS", "-x", "LIFEGOM_MPI_FAULT"])
        // The remote daemon starts as root through the agent, outside mpirun's flags.
        .env("OMPI_ALLOW_RUN_AS_ROOT", "1")
        .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
        .arg(exe);
        c
    }

    /// Bytes host `i` has sent on its link.
    fn sent_bytes(&self, i: usize) -> u64 {
        let out = Command::new("ip")
            .args(["netns", "exec", &self.names[i], "cat"])
            .arg("/sys/class/net/mpi0/statistics/tx_bytes")
            .output()
            .expect("reading the link's counters");
        String::from_utf8_lossy(&out.stdout)
            .trim()
            .parse()
            .expect("a byte count")
    }
}

impl Drop for TwoHosts {
    fn drop(&mut self) {
        // Deleting a namespace deletes the veth end inside it, and with it the pair.
        for ns in &self.names {
            let _ = Command::new("ip").args(["netns", "del", ns]).status();
        }
    }
}

/// `ip ARGS…`, which must succeed (creating namespaces needs root or CAP_NET_ADMIN).
fn ip(args: &[&str]) {
    let out = Command::new("ip")
        .args(args)
        .output()
        .expect("running ip (iproute2)");
    assert!(
        out.status.success(),
        "ip {}: {}",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// `cmd` run to its end ([`Setup::command`]); fails the test on a hang.
fn finish(cmd: Command) -> Output {
    run_with_timeout(cmd, Duration::from_secs(600))
}

/// Runs `cmd`, failing the test (after killing it) if it outlives `limit`: a hang is the
/// failure these tests look for.
fn run_with_timeout(mut cmd: Command, limit: Duration) -> Output {
    let mut child = cmd
        .spawn()
        .expect("starting lifegom-train (is mpirun installed?)");
    let start = Instant::now();
    loop {
        match child.try_wait() {
            Ok(Some(_)) => break,
            Ok(None) if start.elapsed() > limit => {
                let _ = child.kill();
                let out = child.wait_with_output().expect("collecting output");
                panic!(
                    "still running after {limit:?} (a hang):\n{}",
                    String::from_utf8_lossy(&out.stderr)
                );
            }
            Ok(None) => std::thread::sleep(Duration::from_millis(200)),
            Err(e) => panic!("waiting for lifegom-train: {e}"),
        }
    }
    child.wait_with_output().expect("collecting output")
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn succeeded(out: &Output) {
    assert!(out.status.success(), "training failed:\n{}", stderr(out));
}

/// Every float parameter of a checkpoint's model, in visiting order.
fn weights(run: &Path) -> Vec<f32> {
    struct Collect(Vec<f32>);
    impl ModuleVisitor for Collect {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let v = param.val().into_data();
            self.0.extend(v.iter::<f32>());
        }
    }
    #[allow(deprecated)] // Device::ndarray(): the CI backend (design.md §1.4).
    let device = Device::ndarray();
    let loaded = trained::load(&run.join("checkpoints/latest.lgck"), &device)
        .expect("loading the run's checkpoint");
    let mut c = Collect(Vec::new());
    loaded.model.visit(&mut c);
    c.0
}

/// The largest difference relative to the weights' scale.
fn max_relative_difference(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len(), "different models");
    a.iter()
        .zip(b)
        .map(|(x, y)| f64::from((x - y).abs()) / f64::from(x.abs().max(y.abs()).max(1e-3)))
        .fold(0.0, f64::max)
}

fn logged_steps(run: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(run.join("metrics.jsonl"))
        .expect("reading metrics.jsonl")
        .lines()
        .map(|l| serde_json::from_str(l).expect("a JSON line"))
        .collect()
}

#[test]
fn two_ranks_train_what_one_process_trains_with_accumulate_2_and_resume_with_another_count() {
    let s = Setup::new("mpi-equivalence");
    let plain = s.config("plain", "");
    let accumulate = s.config("accumulate", "accumulate = 2");
    let (one, two, mixed) = (s.tmp.join("one"), s.tmp.join("two"), s.tmp.join("mixed"));

    s.train_ok(&accumulate, &one, 3, &Launch::Alone, false);
    s.train_ok(&plain, &two, 3, &Launch::Local(2), false);
    // Two steps on two ranks, the third in one process accumulating both samples.
    s.train_ok(&plain, &mixed, 2, &Launch::Local(2), false);
    s.train_ok(&accumulate, &mixed, 3, &Launch::Alone, true);

    let reference = weights(&one);
    let untrained = {
        let fresh = s.tmp.join("fresh");
        s.train_ok(&plain, &fresh, 0, &Launch::Alone, false);
        weights(&fresh)
    };
    assert!(
        max_relative_difference(&reference, &untrained) > 1e-3,
        "three steps should move the weights"
    );
    for run in [&two, &mixed] {
        let d = max_relative_difference(&reference, &weights(run));
        eprintln!(
            "{}: largest relative weight difference {d:e}",
            run.display()
        );
        assert!(
            d <= 1e-5,
            "{}: weights differ by {d:e} (relative)",
            run.display()
        );
    }

    // Rank 0 alone logged, each step once, with the batch it averaged.
    let log = logged_steps(&two);
    assert_eq!(
        log.iter().map(|l| l["step"].as_u64()).collect::<Vec<_>>(),
        [Some(1), Some(2), Some(3)]
    );
    assert!(log.iter().all(|l| l["batch"] == 2), "{log:?}");
    // The same losses as the process that accumulated (means over the same two samples).
    let one_log = logged_steps(&one);
    for (a, b) in log.iter().zip(&one_log) {
        let (a, b) = (a["total"].as_f64().unwrap(), b["total"].as_f64().unwrap());
        assert!((a - b).abs() <= 1e-5 * a.abs(), "step losses {a} vs {b}");
    }
}

#[test]
fn the_weights_checksum_stops_replicas_that_diverged() {
    let s = Setup::new("mpi-diverge");
    let plain = s.config("plain", "");
    let out = s.tmp.join("run");
    let run = finish(s.command(&plain, &out, 2, &Launch::Local(2), false, Some("diverge:1")));
    let text = stderr(&run);
    assert!(!run.status.success(), "a diverged job must fail:\n{text}");
    assert!(text.contains("weights differ"), "{text}");
    // Nothing from the diverged state was written as a checkpoint.
    assert!(!out.join("checkpoints/latest.lgck").exists(), "{text}");
}

#[test]
fn a_rank_that_dies_ends_the_job_instead_of_hanging_it() {
    let s = Setup::new("mpi-dies");
    let plain = s.config("plain", "");
    let start = Instant::now();
    let run = finish(s.command(
        &plain,
        &s.tmp.join("run"),
        50,
        &Launch::Local(2),
        false,
        Some("fail:1"),
    ));
    let text = stderr(&run);
    assert!(!run.status.success(), "the job must fail:\n{text}");
    assert!(text.contains("exits as if it had died"), "{text}");
    // Well before 50 steps' worth: the surviving rank did not wait for the dead one.
    assert!(
        start.elapsed() < Duration::from_secs(300),
        "{:?}",
        start.elapsed()
    );
}

#[test]
fn two_ranks_on_two_hosts_train_over_tcp() {
    let s = Setup::new("mpi-tcp");
    let plain = s.config("plain", "");
    let accumulate = s.config("accumulate", "accumulate = 2");
    let hosts = TwoHosts::new(&s.tmp);
    let (one, two) = (s.tmp.join("one"), s.tmp.join("two"));
    s.train_ok(&accumulate, &one, 2, &Launch::Alone, false);
    let before = hosts.sent_bytes(1);
    s.train_ok(&plain, &two, 2, &Launch::Network(&hosts), false);
    let sent = hosts.sent_bytes(1) - before;

    let d = max_relative_difference(&weights(&one), &weights(&two));
    eprintln!("over TCP: largest relative weight difference {d:e}, {sent} bytes sent by rank 1");
    assert!(d <= 1e-5, "weights differ by {d:e} (relative)");
    // Rank 1 sent its gradients (4 bytes a parameter) over the link at least once a step.
    let parameters = weights(&one).len() as u64;
    assert!(
        sent >= 2 * 4 * parameters,
        "rank 1 sent {sent} bytes over the link, less than two steps' gradients ({} bytes)",
        2 * 4 * parameters
    );
}

#[test]
fn sigusr1_to_mpirun_stops_every_rank_with_a_checkpoint() {
    let s = Setup::new("mpi-stop");
    let plain = s.config("plain", "");
    let out = s.tmp.join("run");
    let mut child = s
        .command(&plain, &out, 1000, &Launch::Local(2), false, None)
        .spawn()
        .expect("starting mpirun");
    // Wait for the first logged step, then ask the job to stop as a batch system would.
    let start = Instant::now();
    while !out.join("metrics.jsonl").exists()
        || std::fs::read_to_string(out.join("metrics.jsonl"))
            .unwrap_or_default()
            .is_empty()
    {
        assert!(start.elapsed() < Duration::from_secs(300), "no step logged");
        std::thread::sleep(Duration::from_millis(200));
    }
    let status = Command::new("kill")
        .args(["-USR1", &child.id().to_string()])
        .status()
        .expect("kill");
    assert!(status.success());
    let limit = Instant::now();
    while child.try_wait().expect("waiting").is_none() {
        if limit.elapsed() > Duration::from_secs(300) {
            let _ = child.kill();
            panic!("the job did not stop after SIGUSR1");
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    let output = child.wait_with_output().expect("output");
    let text = stderr(&output);
    let summary = String::from_utf8_lossy(&output.stdout);
    assert!(
        summary.contains("\"stop\":\"Interrupted\""),
        "{summary}\n{text}"
    );
    // The checkpoint holds the step the ranks stopped after, well before the 1,000 asked for.
    let header = trained::read_header(&out.join("checkpoints/latest.lgck")).expect("checkpoint");
    let step = header.meta["step"].as_u64().expect("step");
    assert!((1..1000).contains(&step), "{step}");
    assert!(summary.contains(&format!("\"step\":{step}")), "{summary}");
}
