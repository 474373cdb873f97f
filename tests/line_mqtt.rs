//! Publishing to a real MQTT broker (Debian's mosquitto, installed by
//! `.ci/run`) with a real subscribing client: every segment message of a
//! line run arrives, also when the publisher's connection to the broker is
//! cut mid-run and comes back (a TCP proxy between them drops every
//! connection and refuses new ones for 0.8 s; the subscriber stays
//! connected, so what it must see is exactly what was published); a full
//! queue drops (and counts) instead of stalling the line.

use irid::estimate::Mode;
use irid::line::mqtt::{MqttConfig, MqttPublisher};
use irid::line::output::{LineOutput, OutputConfig, Publisher};
use irid::line::rig::WebRig;
use irid::line::run::{run_line, LineLimits};
use irid::line::stats::Lanes;
use rumqttc::{Client, Event, MqttOptions, Packet, QoS};
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

fn mosquitto() -> Option<PathBuf> {
    ["/usr/sbin/mosquitto", "/usr/bin/mosquitto"]
        .iter()
        .map(PathBuf::from)
        .find(|p| p.exists())
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A mosquitto on `port` (persistence in `dir`).
struct Broker {
    bin: PathBuf,
    conf: PathBuf,
    port: u16,
    child: Option<Child>,
}

impl Broker {
    fn start(bin: &Path, dir: &Path) -> Broker {
        let port = free_port();
        // Started as root, mosquitto drops to its own user, which must be
        // able to save the sessions there (else every restart forgets the
        // subscriber's session and what was queued for it).
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(dir, std::fs::Permissions::from_mode(0o777)).unwrap();
        let conf = dir.join("mosquitto.conf");
        std::fs::write(
            &conf,
            format!(
                "listener {port} 127.0.0.1\nallow_anonymous true\npersistence true\npersistence_location {}/\n",
                dir.display()
            ),
        )
        .unwrap();
        let mut b = Broker {
            bin: bin.to_path_buf(),
            conf,
            port,
            child: None,
        };
        b.up();
        b
    }

    fn up(&mut self) {
        let child = Command::new(&self.bin)
            .arg("-c")
            .arg(&self.conf)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        self.child = Some(child);
        let end = Instant::now() + Duration::from_secs(5);
        while std::net::TcpStream::connect(("127.0.0.1", self.port)).is_err() {
            assert!(Instant::now() < end, "mosquitto did not come up");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// SIGTERM: mosquitto saves its sessions and exits.
    fn down(&mut self) {
        if let Some(mut c) = self.child.take() {
            let pid = nix::unistd::Pid::from_raw(c.id() as i32);
            let _ = nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM);
            let _ = c.wait();
        }
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        self.down();
    }
}

/// A TCP proxy to a local port that can cut every connection through it
/// and refuse new ones: a network outage between publisher and broker.
struct Proxy {
    port: u16,
    cut: Arc<AtomicBool>,
    conns: Arc<Mutex<Vec<std::net::TcpStream>>>,
}

impl Proxy {
    fn start(upstream: u16) -> Proxy {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        let cut = Arc::new(AtomicBool::new(false));
        let conns = Arc::new(Mutex::new(Vec::new()));
        let (c, k) = (cut.clone(), conns.clone());
        // Runs until the test process ends.
        std::thread::spawn(move || {
            for client in listener.incoming() {
                let Ok(client) = client else { continue };
                if c.load(Ordering::SeqCst) {
                    continue; // dropped: refused
                }
                let Ok(server) = std::net::TcpStream::connect(("127.0.0.1", upstream)) else {
                    continue;
                };
                let mut held = k.lock().unwrap();
                held.push(client.try_clone().unwrap());
                held.push(server.try_clone().unwrap());
                let (c2, s2) = (client.try_clone().unwrap(), server.try_clone().unwrap());
                std::thread::spawn(move || pump(client, server));
                std::thread::spawn(move || pump(s2, c2));
            }
        });
        Proxy { port, cut, conns }
    }

    fn down(&self) {
        self.cut.store(true, Ordering::SeqCst);
        for s in self.conns.lock().unwrap().drain(..) {
            let _ = s.shutdown(std::net::Shutdown::Both);
        }
    }

    fn up(&self) {
        self.cut.store(false, Ordering::SeqCst);
    }
}

fn pump(mut from: std::net::TcpStream, mut to: std::net::TcpStream) {
    let _ = std::io::copy(&mut from, &mut to);
    let _ = to.shutdown(std::net::Shutdown::Both);
}

/// A subscriber to `irid/line/#` with a persistent session; collects payloads.
fn subscribe(
    port: u16,
    stop: Arc<AtomicBool>,
) -> (Arc<Mutex<Vec<String>>>, std::thread::JoinHandle<()>) {
    let got = Arc::new(Mutex::new(Vec::new()));
    let g = got.clone();
    let h = std::thread::spawn(move || {
        let mut o = MqttOptions::new("irid-test-sub", "127.0.0.1", port);
        o.set_clean_session(false);
        o.set_keep_alive(Duration::from_secs(5));
        let (client, mut conn) = Client::new(o, 16);
        while !stop.load(Ordering::Relaxed) {
            match conn.recv_timeout(Duration::from_millis(50)) {
                Ok(Ok(Event::Incoming(Packet::ConnAck(_)))) => {
                    let _ = client.try_subscribe("irid/line/#", QoS::AtLeastOnce);
                }
                Ok(Ok(Event::Incoming(Packet::Publish(p)))) => {
                    g.lock()
                        .unwrap()
                        .push(String::from_utf8_lossy(&p.payload).into_owned());
                }
                Ok(Err(_)) => std::thread::sleep(Duration::from_millis(50)),
                _ => {}
            }
        }
    });
    (got, h)
}

fn wait_for(what: &str, secs: u64, mut f: impl FnMut() -> bool) {
    let end = Instant::now() + Duration::from_secs(secs);
    while !f() {
        assert!(Instant::now() < end, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn segments_reach_a_subscriber_across_a_connection_outage() {
    let Some(bin) = mosquitto() else {
        eprintln!("SKIPPED: mosquitto is not installed (.ci/run installs it)");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let broker = Broker::start(&bin, dir.path());
    let port = broker.port;
    let stop = Arc::new(AtomicBool::new(false));
    let (got, sub) = subscribe(port, stop.clone());
    // The subscription must be in place before anything is published.
    std::thread::sleep(Duration::from_millis(500));

    // A small line paced at 4× real time (~2.5 s of wall time).
    let mut rig = WebRig::demo().unwrap();
    rig.file.camera.width = 64;
    rig.file.camera.rows_in_view = 16;
    let rig = WebRig::resolve(rig.file, rig.base).unwrap();
    let mut cfg = rig.camera_config();
    cfg.realtime_speed = 4.0;
    let built = rig.build(cfg, Mode::Balanced).unwrap();
    let (mut cam, mut tuner, setup) = (built.camera, built.tuner, built.setup);
    let proxy = Arc::new(Proxy::start(port));
    let mqtt = MqttPublisher::start(MqttConfig::new("127.0.0.1", proxy.port));
    let stats = Arc::new(Mutex::new(None));
    let out_cfg = OutputConfig {
        segment_rows: 8,
        lanes: Lanes::equal(64, 2),
        out_dir: None,
        topic: "irid/line".into(),
    };

    // The broker becomes unreachable after 0.7 s and is back 0.8 s later.
    let p = proxy.clone();
    let outage = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(700));
        p.down();
        std::thread::sleep(Duration::from_millis(800));
        p.up();
    });
    /// Keeps the stats at the end, and the longest a publish call took.
    struct Keep(
        MqttPublisher,
        Arc<Mutex<Option<irid::line::mqtt::MqttStats>>>,
        Arc<Mutex<Duration>>,
    );
    impl Publisher for Keep {
        fn publish(&mut self, t: &str, p: &str) {
            let t0 = Instant::now();
            self.0.publish(t, p);
            let d = t0.elapsed();
            let mut m = self.2.lock().unwrap();
            *m = (*m).max(d);
        }
        fn flush(&mut self) {
            self.0.flush();
            *self.1.lock().unwrap() = Some(self.0.stats());
        }
    }
    let longest = Arc::new(Mutex::new(Duration::ZERO));
    let mut out = LineOutput::new(
        out_cfg,
        None,
        vec![Box::new(Keep(mqtt, stats.clone(), longest.clone()))],
    );
    let frames = 1000u64;
    let rep = run_line(
        &mut cam,
        &mut tuner,
        setup,
        &LineLimits {
            frames: Some(frames),
            frame_timeout: Duration::from_secs(1),
        },
        &mut out,
        &AtomicBool::new(false),
    )
    .unwrap();
    outage.join().unwrap();
    let segments = out.segments;
    drop(out);
    // Never stalled by the outage: no publish call waited for the broker
    // (an append to the queue; the outage lasts 800 ms).
    let st = stats.lock().unwrap().expect("flushed");
    let longest = *longest.lock().unwrap();
    assert!(
        longest < Duration::from_millis(50),
        "a publish took {longest:?}; {st:?}"
    );
    assert!(st.connections >= 2, "no reconnect: {st:?}");
    assert_eq!(st.dropped, 0, "{st:?}");
    assert_eq!(st.delivered, st.queued, "{st:?}");
    assert!(segments > 20, "{rep:?}");
    // Every segment arrived (at least once), in order of first arrival.
    wait_for("all segments", 10, || {
        let g = got.lock().unwrap();
        let seen: std::collections::BTreeSet<u64> = g
            .iter()
            .filter_map(|p| serde_json::from_str::<serde_json::Value>(p).ok())
            .filter_map(|v| v["segment"].as_u64())
            .collect();
        seen.len() as u64 == segments && seen.iter().next_back() == Some(&(segments - 1))
    });
    stop.store(true, Ordering::Relaxed);
    sub.join().unwrap();
}

#[test]
fn a_full_queue_drops_the_oldest_and_counts_without_blocking() {
    // Nothing listens on this port: the publisher can never deliver.
    let port = free_port();
    let mut cfg = MqttConfig::new("127.0.0.1", port);
    cfg.capacity = 4;
    let mut p = MqttPublisher::start(cfg);
    p.set_flush_timeout(Duration::from_millis(100));
    let t0 = Instant::now();
    for i in 0..10 {
        p.publish("irid/line/segment", &format!("{{\"segment\":{i}}}"));
    }
    // Ten appends to a queue: microseconds, not connection timeouts.
    assert!(
        t0.elapsed() < Duration::from_millis(100),
        "{:?}",
        t0.elapsed()
    );
    p.flush();
    let s = p.stats();
    assert_eq!(
        (s.queued, s.dropped, s.waiting, s.delivered),
        (10, 6, 4, 0),
        "{s:?}"
    );
}
