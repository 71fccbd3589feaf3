//! The live view in a real browser: `fleet up --web` on a paced tiny mission, headless
//! Chromium (Debian's `chromium`, installed by scripts/test.sh) opens the page twice, sees
//! every vehicle and the model version advance, logs nothing to the console, and saves a
//! screenshot; the mission outlives a killed view and the open page reconnects to a new one.
//! `/api/state` says the same; bad requests get 4xx; a lost vehicle is marked; a view that
//! missed the model's puts catches up.

use fleet_mission::config::MissionConfig;
use hetfleet_tests::*;
use std::io::Write;
use std::path::Path;
use std::process::{Command, Stdio};

fn version(s: &serde_json::Value) -> u64 {
    s["model"]["version"].as_u64().unwrap_or(0)
}

/// Headless Chromium driven over the DevTools protocol on a pipe (`--remote-debugging-pipe`:
/// NUL-separated JSON on fds 3 and 4, no WebSocket client needed): it opens a page, reads
/// values out of it while it runs, and records every console message and uncaught exception.
struct Chromium {
    child: std::process::Child,
    to: std::fs::File,
    from: std::io::BufReader<std::fs::File>,
    next: u64,
    session: String,
    console: Vec<String>,
}

impl Chromium {
    fn open(url: &str, dir: &Path) -> Self {
        use std::os::fd::FromRawFd;
        use std::os::unix::process::CommandExt;
        let pipe = || {
            let mut fds = [0; 2];
            assert_eq!(unsafe { libc::pipe2(fds.as_mut_ptr(), libc::O_CLOEXEC) }, 0);
            (fds[0], fds[1])
        };
        let ((chrome_reads, we_write), (we_read, chrome_writes)) = (pipe(), pipe());
        let mut c = Command::new("chromium");
        c.args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            "--remote-debugging-pipe",
            "--window-size=1366,1500",
        ]);
        c.arg(format!("--user-data-dir={}", dir.join("chromium-profile").display()));
        c.stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join("chromium.log")).unwrap());
        // SAFETY: only async-signal-safe calls between fork and exec. Copies above 10 first, so
        // neither target fd is clobbered; dup2 clears close-on-exec on 3 and 4.
        unsafe {
            c.pre_exec(move || {
                let (r, w) = (
                    libc::fcntl(chrome_reads, libc::F_DUPFD, 10),
                    libc::fcntl(chrome_writes, libc::F_DUPFD, 10),
                );
                if r < 0 || w < 0 || libc::dup2(r, 3) < 0 || libc::dup2(w, 4) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let child = c
            .spawn()
            .expect("chromium runs (scripts/test.sh installs Debian's chromium)");
        unsafe {
            libc::close(chrome_reads);
            libc::close(chrome_writes);
        }
        let (to, from) = unsafe {
            (
                std::fs::File::from_raw_fd(we_write),
                std::io::BufReader::new(std::fs::File::from_raw_fd(we_read)),
            )
        };
        let mut b = Self {
            child,
            to,
            from,
            next: 0,
            session: String::new(),
            console: vec![],
        };
        let target = b.call("Target.createTarget", serde_json::json!({ "url": "about:blank" }))["targetId"]
            .as_str()
            .unwrap()
            .to_string();
        b.session = b.call(
            "Target.attachToTarget",
            serde_json::json!({ "targetId": target, "flatten": true }),
        )["sessionId"]
            .as_str()
            .unwrap()
            .to_string();
        for domain in ["Runtime.enable", "Log.enable", "Page.enable"] {
            b.call(domain, serde_json::json!({}));
        }
        b.call("Page.navigate", serde_json::json!({ "url": url }));
        b
    }

    /// One command (on the page's session once attached); events seen meanwhile are kept.
    fn call(&mut self, method: &str, params: serde_json::Value) -> serde_json::Value {
        use std::io::BufRead;
        self.next += 1;
        let mut msg = serde_json::json!({ "id": self.next, "method": method, "params": params });
        if !self.session.is_empty() {
            msg["sessionId"] = self.session.clone().into();
        }
        let mut bytes = serde_json::to_vec(&msg).unwrap();
        bytes.push(0);
        self.to.write_all(&bytes).expect("writing to chromium");
        loop {
            let mut buf = vec![];
            let n = self.from.read_until(0, &mut buf).expect("reading from chromium");
            assert!(n > 0, "chromium closed its pipe");
            buf.pop();
            let m: serde_json::Value = serde_json::from_slice(&buf).expect("chromium speaks JSON");
            match m["method"].as_str() {
                Some("Runtime.consoleAPICalled") => self
                    .console
                    .push(format!("console.{}: {}", m["params"]["type"], m["params"]["args"])),
                Some("Runtime.exceptionThrown") => self
                    .console
                    .push(format!("exception: {}", m["params"]["exceptionDetails"])),
                Some("Log.entryAdded") => self.console.push(format!("log: {}", m["params"]["entry"])),
                _ => {}
            }
            if m["id"].as_u64() == Some(self.next) {
                assert!(m.get("error").is_none(), "{method}: {m}");
                return m["result"].clone();
            }
        }
    }

    /// A JavaScript expression's value in the page.
    fn eval(&mut self, js: &str) -> serde_json::Value {
        self.call(
            "Runtime.evaluate",
            serde_json::json!({ "expression": js, "returnByValue": true }),
        )["result"]["value"]
            .clone()
    }

    fn screenshot(&mut self, path: &Path) {
        use base64::Engine as _;
        let png = self.call("Page.captureScreenshot", serde_json::json!({ "format": "png" }))["data"]
            .as_str()
            .unwrap()
            .to_string();
        std::fs::write(path, base64::engine::general_purpose::STANDARD.decode(png).unwrap()).unwrap();
    }
}

impl Drop for Chromium {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[test]
fn a_real_browser_sees_every_vehicle_and_the_model_advance_without_console_errors() {
    let dir = scratch("web");
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let mission = tiny_mission(&dir, std::slice::from_ref(&ep), std::slice::from_ref(&ep));
    edit(
        &mission,
        "plan_timeout_ms = 20000",
        "plan_timeout_ms = 1500\nstep_ms = 800",
    );
    let port = free_port();
    let mut procs = Procs::default();
    let up = Command::new(bin("fleet"))
        .args([
            "up",
            mission.to_str().unwrap(),
            "--out",
            dir.join("run").to_str().unwrap(),
            "--web",
            &format!("127.0.0.1:{port}"),
            "--web-linger-s",
            "0",
        ])
        .current_dir(root())
        .stdout(std::fs::File::create(dir.join("up.log")).unwrap())
        .stderr(std::fs::File::create(dir.join("up.err")).unwrap())
        .spawn()
        .expect("fleet up");
    procs.0.push(up);
    let url = format!("http://127.0.0.1:{port}/");
    eventually(60, "the view has a model", || {
        web_state(port).is_some_and(|s| version(&s) >= 1)
    });

    // The JSON endpoint the page uses, as documented in docs/guide/watching.md.
    let s = web_state(port).unwrap();
    let ids: Vec<String> = MissionConfig::load(Some(&mission))
        .unwrap()
        .vehicles()
        .into_iter()
        .map(|v| v.id.into())
        .collect();
    let vehicles = s["vehicles"].as_array().unwrap();
    assert_eq!(vehicles.len(), ids.len());
    for v in vehicles {
        for field in ["id", "kind", "position", "mode", "link", "outbox_depth"] {
            assert!(v.get(field).is_some(), "vehicle without {field}: {v}");
        }
    }
    for field in ["batches", "duplicates", "rejected", "waiting_for", "next_epoch"] {
        assert!(s["server"].get(field).is_some(), "server without {field}: {s}");
    }
    assert!(s["model"]["epoch"].is_u64());

    // Bad requests: 4xx, and the view still answers.
    assert_eq!(http(port, "POST", "/api/state").map(|r| r.0), Some(405));
    assert_eq!(http(port, "GET", "/no/such/thing").map(|r| r.0), Some(404));
    assert_eq!(http(port, "GET", "/api/state?x=%ff%00").map(|r| r.0), Some(200));
    assert_eq!(http(port, "DELETE", "/").map(|r| r.0), Some(405));
    let (status, npy) = http(port, "GET", "/api/estimate.npy").unwrap();
    assert_eq!(status, 200);
    assert!(npy.get(..12).is_some_and(|h| h.contains("NUMPY")), "an .npy file");

    // The browser: every vehicle listed, the model version advancing on the page (pushed,
    // not reloaded), nothing on the console, and a screenshot.
    let mut page = Chromium::open(&url, &dir);
    let shown = |p: &mut Chromium| {
        p.eval("Number(document.getElementById('version').textContent) || 0")
            .as_u64()
            .unwrap_or(0)
    };
    eventually(30, "the page shows a model", || shown(&mut page) >= 1);
    let v1 = shown(&mut page);
    let listed = page.eval("[...document.querySelectorAll('#vehicles tr')].map(r => r.dataset.id)");
    for id in &ids {
        assert!(
            listed.as_array().unwrap().iter().any(|x| x == id),
            "the page lists {id}: {listed}"
        );
    }
    assert!(
        page.console.is_empty(),
        "the page logged to the console: {:#?}",
        page.console
    );
    // The view dies mid-mission: the mission goes on (fleet up ends 0 below), the page says
    // it is reconnecting, and once a view is back on the same address the same page (not
    // reloaded) is live again and follows the model.
    let watch: Vec<u32> = pids_with(&format!("127.0.0.1:{port}"))
        .into_iter()
        .filter(|p| cmdline(*p).contains("fleet-watch"))
        .collect();
    assert_eq!(watch.len(), 1, "one fleet-watch");
    unsafe { libc::kill(watch[0] as i32, libc::SIGKILL) };
    let badge = |p: &mut Chromium| {
        p.eval("document.getElementById('conn').textContent")
            .as_str()
            .unwrap_or("")
            .to_string()
    };
    eventually(10, "the page says it is reconnecting", || {
        badge(&mut page) == "reconnecting"
    });
    let mut view = Procs::default();
    let truth = dir.join("run/truth.npy");
    let restarted = Command::new(bin("fleet-watch"))
        .args([
            "--mission",
            mission.to_str().unwrap(),
            "--truth",
            truth.to_str().unwrap(),
            "--http",
            &format!("127.0.0.1:{port}"),
        ])
        .stderr(std::fs::File::create(dir.join("watch-restarted.log")).unwrap())
        .spawn()
        .unwrap();
    view.0.push(restarted);
    eventually(30, "the page is live again", || badge(&mut page) == "live");
    eventually(60, "the page's model advances", || shown(&mut page) > v1);
    let v2 = shown(&mut page);
    let shot = dir.join("live-view.png");
    page.screenshot(&shot);
    let png = std::fs::read(&shot).expect("a screenshot");
    assert!(
        png.starts_with(b"\x89PNG") && png.len() > 10_000,
        "a real screenshot ({} bytes)",
        png.len()
    );
    // After the kill, only the browser's own notes that the event stream broke and could
    // not reconnect until the view was back.
    let unexpected: Vec<_> = page
        .console
        .iter()
        .filter(|l| !(l.starts_with("log: ") && l.contains("\"source\":\"network\"") && l.contains("/api/events")))
        .collect();
    assert!(unexpected.is_empty(), "the page logged to the console: {unexpected:#?}");
    println!(
        "browser saw model v{v1}, the view killed and back, then v{v2}; {} vehicles; screenshot {}",
        ids.len(),
        shot.display()
    );
    // A laptop's screen: nothing wider than the window.
    let wide = page.eval("document.documentElement.scrollWidth - document.documentElement.clientWidth");
    assert!(
        wide.as_i64().is_some_and(|w| w <= 0),
        "the page is {wide} px wider than a 1,366 px window"
    );
    // A normal end is no alarm: "finished" while the view is up, and after it stops.
    procs.wait_all(120);
    eventually(30, "the page says the mission finished", || {
        badge(&mut page) == "finished"
    });
    drop(view);
    std::thread::sleep(std::time::Duration::from_secs(2));
    assert_eq!(badge(&mut page), "finished", "the view stopped after a normal end");
    drop(page);
}

#[test]
fn a_vehicle_that_goes_silent_is_marked_lost_within_the_lease_and_a_public_address_needs_a_credential() {
    let dir = scratch("web-silent");
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let mission = paced_mission(&dir, std::slice::from_ref(&ep), std::slice::from_ref(&ep), 200);
    let m = mission.to_str().unwrap();

    // Bound beyond loopback without a credential: refused, exit 2, one line naming the flag.
    let out = Command::new(bin("fleet-watch"))
        .args(["--mission", m, "--http", "0.0.0.0:1"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--credential"));

    let (out_dir, state_dir) = (dir.join("out"), dir.join("state"));
    let mut procs = Procs::default();
    let server = start_server(
        &mut procs,
        &[
            "--mission",
            m,
            "--out",
            out_dir.to_str().unwrap(),
            "--state-dir",
            state_dir.to_str().unwrap(),
            "--exit-when-done",
        ],
        &dir.join("server.log"),
    );
    let (port, _) = start_view(&mut procs, m, &dir);
    let mut boat2 = 0;
    for v in MissionConfig::load(Some(&mission)).unwrap().vehicles() {
        let args = [
            "--mission",
            m,
            "--id",
            &v.id,
            "--state-dir",
            state_dir.to_str().unwrap(),
        ];
        let i = start_vehicle(&mut procs, &[], &args, &dir.join(format!("{}.log", v.id)));
        if v.id == "boat-2" {
            boat2 = i;
        }
    }
    let link = |s: &serde_json::Value, id: &str| {
        s["vehicles"]
            .as_array()
            .unwrap()
            .iter()
            .find(|v| v["id"] == id)
            .map(|v| v["link"].as_str().unwrap_or("").to_string())
            .unwrap()
    };
    eventually(60, "boat-2's link is up", || {
        web_state(port).is_some_and(|s| link(&s, "boat-2") == "up")
    });
    server.epoch(1, 60);
    procs.kill(boat2);
    let killed = std::time::Instant::now();
    eventually(10, "boat-2 marked lost", || {
        web_state(port).is_some_and(|s| link(&s, "boat-2") == "lost")
    });
    let after = killed.elapsed().as_secs_f64();
    // Its liveliness token goes when the link does (at once for a closed socket, within the
    // 1 s lease for a silent one); the view pushes every 0.25 s.
    assert!(after < 1.5, "marked lost {after:.2} s after it died");
    let s = web_state(port).unwrap();
    assert!(s["vehicles"]
        .as_array()
        .unwrap()
        .iter()
        .find(|v| v["id"] == "boat-2")
        .unwrap()["lost_since_s"]
        .is_f64());
    assert_eq!(link(&s, "boat-1"), "up", "the others are not");
    println!("boat-2 marked lost {after:.2} s after kill -9 (lease 1 s)");
}

/// `fleet-watch` on `mission` at a free loopback port, its log in `dir`: the port and the pid.
fn start_view(procs: &mut Procs, mission: &str, dir: &Path) -> (u16, i32) {
    let port = free_port();
    let watch = Command::new(bin("fleet-watch"))
        .args(["--mission", mission, "--http", &format!("127.0.0.1:{port}")])
        .stderr(std::fs::File::create(dir.join("watch.log")).unwrap())
        .spawn()
        .unwrap();
    let pid = watch.id() as i32;
    procs.0.push(watch);
    (port, pid)
}

/// A view that could not hear the model go by (stopped past its 1 s link lease while the whole
/// mission ran, as a laptop asleep or a view that joins as the last put leaves) shows the
/// final model once it is back: the server's status says a newer version, and it asks.
#[test]
fn a_view_that_was_away_while_the_model_went_by_catches_up_from_the_servers_status() {
    let dir = scratch("web-away");
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let mission = tiny_mission(&dir, std::slice::from_ref(&ep), std::slice::from_ref(&ep));
    edit(&mission, "listen = [", "lease_ms = 1000\nlisten = [");
    let (m, state) = (mission.to_str().unwrap(), dir.join("state"));
    let mut procs = Procs::default();
    let server = start_server(
        &mut procs,
        &["--mission", m, "--state-dir", state.to_str().unwrap()],
        &dir.join("server.log"),
    );
    let (port, pid) = start_view(&mut procs, m, &dir);
    eventually(30, "the view hears the server", || {
        web_state(port).is_some_and(|s| s["server"].is_object())
    });
    unsafe { libc::kill(pid, libc::SIGSTOP) };
    // Past the lease: the server has closed the view's session before the first model.
    std::thread::sleep(std::time::Duration::from_secs(3));
    start_vehicles(&mut procs, &mission, state.to_str().unwrap(), &dir, &[]);
    let summary = server.finished(120);
    unsafe { libc::kill(pid, libc::SIGCONT) };
    eventually(15, "the view has the final model", || {
        web_state(port).is_some_and(|s| version(&s) == summary.model_version)
    });
}

/// The Foxglove WebSocket client (`tests/py/foxglove_ws.py`) at `url`: what it printed.
fn foxglove_client(url: &str, vehicles: &str, mode: &str) -> String {
    let o = Command::new("python3")
        .args(["tests/py/foxglove_ws.py", url, vehicles, mode])
        .current_dir(root())
        .output()
        .expect("python3");
    let said = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(o.status.success(), "{said}{}", String::from_utf8_lossy(&o.stderr));
    said
}

#[test]
fn foxglove_sees_the_vehicles_and_the_grid_live_and_a_public_address_needs_a_credential() {
    let dir = scratch("foxglove");
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    let mission = paced_mission(&dir, std::slice::from_ref(&ep), std::slice::from_ref(&ep), 150);
    let m = mission.to_str().unwrap();

    // Beyond loopback without a credential: refused, exit 2, one line naming the flag.
    let out = Command::new(bin("fleet-watch"))
        .args(["--mission", m, "--http", "127.0.0.1:0", "--foxglove", "0.0.0.0:1"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("--foxglove") && err.contains("--credential"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");

    // With a credential: a client without it is refused (401); with it in the URL, let in.
    let port = free_port();
    // In `Procs`, so that a client that fails does not leave the view running.
    let mut watch = Procs::default();
    let child = Command::new(bin("fleet-watch"))
        .args([
            "--mission",
            m,
            "--http",
            "127.0.0.1:0",
            "--credential",
            "ops:s3cret@sea",
        ])
        .args(["--foxglove", &format!("127.0.0.1:{port}")])
        .stderr(std::fs::File::create(dir.join("watch.log")).unwrap())
        .spawn()
        .unwrap();
    watch.0.push(child);
    let url = format!("ws://127.0.0.1:{port}");
    let refused = foxglove_client(&url, "", "refused");
    let admitted = foxglove_client(&format!("{url}/?credential=ops%3As3cret%40sea"), "", "connect");
    drop(watch);
    assert!(refused.starts_with("refused 401"), "{refused}");
    assert!(admitted.starts_with("connected"), "{admitted}");

    // `fleet up --foxglove`: while the mission runs, the client subscribes and receives every
    // vehicle's LocationFix and the estimate's Grid.
    let port = free_port();
    let mut up = Command::new(bin("fleet"))
        .args(["up", m, "--out", dir.join("run").to_str().unwrap()])
        .args(["--foxglove", &format!("127.0.0.1:{port}")])
        .current_dir(root())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.join("up.log")).unwrap())
        .spawn()
        .unwrap();
    let vehicles: Vec<String> = MissionConfig::load(Some(&mission))
        .unwrap()
        .vehicles()
        .into_iter()
        .map(|v| v.id.to_string())
        .collect();
    let said = foxglove_client(&format!("ws://127.0.0.1:{port}"), &vehicles.join(","), "data");
    assert!(
        up.wait().unwrap().success(),
        "fleet up failed: see {}",
        dir.join("up.log").display()
    );
    assert!(said.starts_with("ok") && said.contains("/foxglove/estimate"), "{said}");
    println!("{said}");
}
