//! `irid run --serve`: the live page is served, its server-sent events
//! carry each new sweep's summary (sweep numbers increasing), `/map.png`
//! is the latest thickness picture and `/history.json` the trend. Plain
//! HTTP over a socket, and the page in headless Chromium (two screenshots:
//! the map and the trend drawn, and the page changing as sweeps arrive).

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn get(addr: &str, path: &str) -> Vec<u8> {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    write!(
        s,
        "GET {path} HTTP/1.0\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut buf = Vec::new();
    s.read_to_end(&mut buf).unwrap();
    let split = buf.windows(4).position(|w| w == b"\r\n\r\n").unwrap();
    assert!(
        buf.starts_with(b"HTTP/1.0 200") || buf.starts_with(b"HTTP/1.1 200"),
        "{path}"
    );
    buf[split + 4..].to_vec()
}

fn sweep_of(json: &str) -> u64 {
    let v: serde_json::Value = serde_json::from_str(json).unwrap();
    v["sweep"].as_u64().unwrap()
}

#[test]
fn the_live_page_its_events_and_the_map_update() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_irid"))
        .args([
            "run",
            "--sweeps",
            "400",
            "--no-maps",
            "--serve",
            "127.0.0.1:0",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut err = BufReader::new(child.stderr.take().unwrap());
    let mut addr = None;
    let mut line = String::new();
    while err.read_line(&mut line).unwrap() > 0 {
        if let Some(rest) = line.trim().strip_prefix("irid: live view at http://") {
            addr = Some(rest.trim_end_matches('/').to_string());
            break;
        }
        line.clear();
    }
    std::thread::spawn(move || std::io::copy(&mut err, &mut std::io::sink()));
    let addr = addr.expect("the run announces its address");
    let result = std::panic::catch_unwind(|| {
        let page = String::from_utf8(get(&addr, "/")).unwrap();
        assert!(page.contains("EventSource('/events')") && page.contains("id=\"trend\""));
        // Two events from the stream, in order.
        let mut s = TcpStream::connect(&addr).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
        write!(s, "GET /events HTTP/1.1\r\nHost: {addr}\r\n\r\n").unwrap();
        let mut r = BufReader::new(s);
        let mut sweeps = Vec::new();
        let t0 = Instant::now();
        let mut l = String::new();
        while sweeps.len() < 2 && t0.elapsed() < Duration::from_secs(120) {
            l.clear();
            if r.read_line(&mut l).unwrap() == 0 {
                break;
            }
            // Chunked encoding puts sizes on their own lines; data lines
            // are whole.
            if let Some(j) = l.trim().strip_prefix("data: ") {
                sweeps.push(sweep_of(j));
            }
        }
        assert_eq!(sweeps.len(), 2, "two sweep events");
        assert!(sweeps[1] > sweeps[0], "{sweeps:?}");
        // The map: a PNG of the latest sweep, mostly viridis pixels.
        let png = irid::render::canvas::decode_png(&get(&addr, "/map.png")).unwrap();
        let viridis = png
            .data
            .chunks(3)
            .filter(|p| {
                (0..=100).any(|i| {
                    let v = irid::render::map::viridis(i as f64 / 100.0);
                    (0..3).all(|k| (p[k] as i32 - v[k] as i32).abs() <= 3)
                })
            })
            .count();
        assert!(
            viridis > png.width * png.height / 10,
            "{viridis} viridis pixels"
        );
        // Open pages hold event streams; more of them than the server has
        // request threads (8) must not shut the page out.
        let held: Vec<TcpStream> = (0..12)
            .map(|_| {
                let mut s = TcpStream::connect(&addr).unwrap();
                write!(s, "GET /events HTTP/1.1\r\nHost: {addr}\r\n\r\n").unwrap();
                s
            })
            .collect();
        std::thread::sleep(Duration::from_millis(300));
        let page = String::from_utf8(get(&addr, "/")).unwrap();
        assert!(
            page.contains("id=\"trend\""),
            "page served beside 12 streams"
        );
        drop(held);
        let hist: serde_json::Value = serde_json::from_slice(&get(&addr, "/history.json")).unwrap();
        let hist = hist.as_array().unwrap();
        assert!(hist.len() >= 2);
        let last = &hist[hist.len() - 1];
        let mean = last["thickness_mean_nm"].as_f64().unwrap();
        assert!(
            (419.0..561.0).contains(&mean),
            "mean {mean} within the cylinder's 420–560 nm"
        );
    });
    let browser = std::panic::catch_unwind(|| browser_check(&addr));
    child.kill().ok();
    child.wait().ok();
    if let Err(e) = result {
        std::panic::resume_unwind(e);
    }
    if let Err(e) = browser {
        std::panic::resume_unwind(e);
    }
}

/// A screenshot of the page in headless Chromium, taken when it has
/// loaded (at most 8 s): the trend so far comes inline and the map is part
/// of the load, so a loaded page is a drawn page.
/// Also Chromium's stderr, to say why a screenshot is missing or blank.
fn screenshot(addr: &str) -> (Option<irid::render::canvas::RgbImage>, String) {
    let dir = tempfile::tempdir().unwrap();
    let shot = dir.path().join("shot.png");
    let mut c = Command::new("chromium")
        .args(["--headless", "--no-sandbox", "--disable-gpu"])
        .args(["--disable-background-networking", "--no-first-run"])
        .arg(format!(
            "--user-data-dir={}",
            dir.path().join("profile").display()
        ))
        .args(["--timeout=8000", "--window-size=1000,900"])
        .arg(format!("--screenshot={}", shot.display()))
        .arg(format!("http://{addr}/"))
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.path().join("stderr.txt")).unwrap())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while c.try_wait().unwrap().is_none() {
        if t0.elapsed() > Duration::from_secs(90) {
            c.kill().ok();
            panic!("chromium did not finish in 90 s");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let img = std::fs::read(&shot)
        .ok()
        .and_then(|b| irid::render::canvas::decode_png(&b).ok());
    let log = std::fs::read_to_string(dir.path().join("stderr.txt")).unwrap_or_default();
    (img, log)
}

fn count(img: &irid::render::canvas::RgbImage, f: impl Fn(&[u8]) -> bool) -> usize {
    img.data.chunks(3).filter(|p| f(p)).count()
}

fn browser_check(addr: &str) {
    if Command::new("chromium").arg("--version").output().is_err() {
        eprintln!("SKIPPED browser check: `chromium` is not installed (.ci/run installs it)");
        return;
    }
    let near =
        |p: &[u8], c: [u8; 3], tol: i32| (0..3).all(|k| (p[k] as i32 - c[k] as i32).abs() <= tol);
    // The map: the picture's viridis ends (the cylinder spans its range);
    // the trend: its ±spread band (rgba(33,145,140,0.25) over white).
    let drawn = |shot: &irid::render::canvas::RgbImage| {
        let purple = count(shot, |p| near(p, irid::render::map::viridis(0.02), 6));
        let yellow = count(shot, |p| near(p, irid::render::map::viridis(0.98), 6));
        let band = count(shot, |p| near(p, [200, 228, 227], 4));
        (purple, yellow, band)
    };
    let ok = |(purple, yellow, band): (usize, usize, usize)| {
        purple > 200 && yellow > 200 && band > 20_000
    };
    // A loaded machine may not have drawn the page by the screenshot's
    // deadline: up to four tries each.
    let shoot = || {
        let mut last = (0, 0, 0);
        let mut why = String::new();
        for _ in 0..4 {
            let (shot, log) = screenshot(addr);
            let Some(shot) = shot else {
                why = format!("no screenshot; chromium said:\n{log}");
                continue;
            };
            last = drawn(&shot);
            if ok(last) {
                return shot;
            }
            // The page's own answer at that moment, beside Chromium's log.
            let page = get(addr, "/").len();
            why = format!("GET / gave {page} bytes; chromium said:\n{log}");
        }
        let (purple, yellow, band) = last;
        panic!("map: {purple} purple, {yellow} yellow pixels; trend band: {band} pixels; {why}");
    };
    let first = shoot();
    let second = shoot();
    // Later sweeps: the page changed (sweep number, trend, map noise).
    let differ = first
        .data
        .chunks(3)
        .zip(second.data.chunks(3))
        .filter(|(a, b)| a != b)
        .count();
    assert!(
        differ > 100,
        "the page did not update: {differ} pixels differ"
    );
}
