//! `irid run --serve ADDR`: a live page for an operator — the latest
//! thickness map, the per-sweep trend of mean and spread, the valid
//! fraction, drops and latency, updated by server-sent events. No build
//! step, no external network: one inline HTML page.
//!
//! It never slows the pipeline: the run's sink hands each finished map to
//! a renderer thread through a one-slot channel with `try_send` (a map
//! arriving while the previous one is still being drawn is skipped), and
//! the HTTP threads only read the latest picture and summaries. Each open
//! page's event stream runs on its own thread (at most [`MAX_STREAMS`]), so
//! open pages never take the threads that serve the page and the map.

use crate::estimate::ParamMaps;
use crate::pipeline::output::SweepSummary;
use crate::render::map::{render_map, MapStyle};
use crossbeam_channel::{bounded, Sender, TrySendError};
use std::io::Write;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

/// Summaries kept for the trend.
pub const HISTORY: usize = 600;

/// Event streams served at once (each holds a thread while its page is
/// open).
pub const MAX_STREAMS: usize = 64;

/// Event streams open now.
static STREAMS: AtomicUsize = AtomicUsize::new(0);

#[derive(Default)]
struct State {
    png: Vec<u8>,
    history: Vec<String>,
    version: u64,
}

type Shared = Arc<(Mutex<State>, Condvar)>;

/// The live view: give it every sweep with [`LiveView::offer`].
pub struct LiveView {
    tx: Sender<(SweepSummary, ParamMaps)>,
    /// Where it listens (the port resolved when `:0` was asked).
    pub addr: String,
}

impl LiveView {
    /// Listen on `addr` and start the renderer and HTTP threads.
    pub fn start(addr: &str) -> anyhow::Result<LiveView> {
        let server =
            tiny_http::Server::http(addr).map_err(|e| anyhow::anyhow!("--serve {addr}: {e}"))?;
        let addr = server
            .server_addr()
            .to_ip()
            .map_or_else(|| addr.to_string(), |a| a.to_string());
        let shared: Shared = Arc::default();
        let (tx, rx) = bounded::<(SweepSummary, ParamMaps)>(1);
        let sh = shared.clone();
        std::thread::Builder::new()
            .name("live-render".into())
            .spawn(move || {
                for (s, maps) in rx {
                    let png = render_png(&maps, s.sweep);
                    let (lock, cv) = &*sh;
                    let Ok(mut st) = lock.lock() else { return };
                    if let Some(png) = png {
                        st.png = png;
                    }
                    st.history.push(s.json());
                    if st.history.len() > HISTORY {
                        st.history.remove(0);
                    }
                    st.version += 1;
                    cv.notify_all();
                }
            })?;
        let server = Arc::new(server);
        for i in 0..8 {
            let (server, shared) = (server.clone(), shared.clone());
            std::thread::Builder::new()
                .name(format!("live-http-{i}"))
                .spawn(move || {
                    for req in server.incoming_requests() {
                        respond(req, &shared);
                    }
                })?;
        }
        Ok(LiveView { tx, addr })
    }

    /// Offer a finished sweep; skipped (never waited for) when the renderer
    /// is busy.
    pub fn offer(&self, s: &SweepSummary, maps: &ParamMaps) {
        if let Err(TrySendError::Full(_)) = self.tx.try_send((s.clone(), maps.clone())) {
            // The page shows the next one.
        }
    }
}

fn render_png(maps: &ParamMaps, sweep: u64) -> Option<Vec<u8>> {
    let c = crate::io::exr_maps::Channels::from_maps(maps);
    let style = MapStyle {
        channel: "thickness_nm".into(),
        range: None,
        title: format!("film thickness, sweep {sweep}"),
    };
    render_map(&c, &style).ok()?.image.to_png().ok()
}

fn header(k: &str, v: &str) -> tiny_http::Header {
    tiny_http::Header::from_bytes(k.as_bytes(), v.as_bytes()).expect("ASCII header")
}

fn respond(req: tiny_http::Request, shared: &Shared) {
    let url = req.url().split('?').next().unwrap_or("").to_string();
    let (lock, _) = &**shared;
    let _ = match url.as_str() {
        "/" => {
            let page = lock.lock().map(|s| page(&s)).unwrap_or_default();
            req.respond(
                tiny_http::Response::from_string(page)
                    .with_header(header("Content-Type", "text/html; charset=utf-8"))
                    .with_header(header("Cache-Control", "no-store")),
            )
        }
        "/map.png" => {
            let png = lock.lock().map(|s| s.png.clone()).unwrap_or_default();
            if png.is_empty() {
                req.respond(tiny_http::Response::from_string("no map yet").with_status_code(503))
            } else {
                req.respond(
                    tiny_http::Response::from_data(png)
                        .with_header(header("Content-Type", "image/png"))
                        .with_header(header("Cache-Control", "no-store")),
                )
            }
        }
        "/history.json" => {
            let h = lock.lock().map(|s| s.history.join(",")).unwrap_or_default();
            req.respond(
                tiny_http::Response::from_string(format!("[{h}]"))
                    .with_header(header("Content-Type", "application/json")),
            )
        }
        "/events" => {
            // Each stream on its own thread, so that open pages never take
            // the threads that serve the page and the map (a closed page's
            // stream ends at its next write: ≤ 15 s). At most
            // `MAX_STREAMS` at once; beyond, 503.
            if STREAMS.fetch_add(1, Ordering::SeqCst) >= MAX_STREAMS {
                STREAMS.fetch_sub(1, Ordering::SeqCst);
                req.respond(
                    tiny_http::Response::from_string("too many event streams")
                        .with_status_code(503),
                )
            } else {
                let shared = shared.clone();
                let spawned = std::thread::Builder::new()
                    .name("live-events".into())
                    .spawn(move || {
                        // Written straight to the socket and flushed per
                        // event (a chunked response would sit in the
                        // encoder's buffer).
                        let mut w = req.into_writer();
                        stream_events(&mut *w, &shared);
                        STREAMS.fetch_sub(1, Ordering::SeqCst);
                    });
                if spawned.is_err() {
                    STREAMS.fetch_sub(1, Ordering::SeqCst);
                }
                Ok(())
            }
        }
        _ => req.respond(tiny_http::Response::from_string("not found").with_status_code(404)),
    };
}

/// A server-sent event stream: one `data:` line (the sweep's summary JSON)
/// per new sweep, a comment every 15 s to keep the connection alive; ends
/// when the client goes.
fn stream_events(w: &mut dyn Write, shared: &Shared) {
    let head = "HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-store\r\nConnection: close\r\n\r\n";
    if w.write_all(head.as_bytes())
        .and_then(|_| w.flush())
        .is_err()
    {
        return;
    }
    let (lock, cv) = &**shared;
    let mut seen = 0;
    loop {
        let msg = {
            let Ok(st) = lock.lock() else { return };
            let Ok((st, _)) =
                cv.wait_timeout_while(st, Duration::from_secs(15), |s| s.version == seen)
            else {
                return;
            };
            if st.version == seen {
                ": keep-alive\n\n".to_string()
            } else {
                seen = st.version;
                format!(
                    "data: {}\n\n",
                    st.history.last().cloned().unwrap_or_default()
                )
            }
        };
        if w.write_all(msg.as_bytes()).and_then(|_| w.flush()).is_err() {
            return;
        }
    }
}

/// The page with the trend so far inline (`</` escaped inside the script).
fn page(st: &State) -> String {
    PAGE.replace("/*HISTORY*/", &st.history.join(",").replace("</", "<\\/"))
}

const PAGE: &str = r##"<!doctype html>
<html><head><meta charset="utf-8"><title>irid live</title>
<style>
body{font-family:sans-serif;margin:16px;background:#fafafa}
#stats span{display:inline-block;margin-right:18px}
canvas{background:#fff;border:1px solid #ccc}
img{max-width:100%;border:1px solid #ccc;background:#fff}
</style></head><body>
<h2>irid live: film thickness</h2>
<div id="stats"><span>sweep <b id="sweep">-</b></span><span>valid <b id="valid">-</b></span>
<span>dropped <b id="drops">-</b></span><span>latency <b id="lat">-</b></span></div>
<p><img id="map" alt="latest thickness map"></p>
<h3>mean &plusmn; spread per sweep (nm)</h3>
<canvas id="trend" width="900" height="260"></canvas>
<script>
const hist = [];
function fmt(v, d){ return (v === null || v === undefined) ? '-' : Number(v).toFixed(d); }
function draw(){
  const c = document.getElementById('trend'), g = c.getContext('2d');
  g.clearRect(0,0,c.width,c.height);
  const pts = hist.filter(h => h.thickness_mean_nm !== null);
  if (!pts.length) return;
  let lo = Infinity, hi = -Infinity;
  for (const h of pts){ lo = Math.min(lo, h.thickness_mean_nm - h.thickness_std_nm); hi = Math.max(hi, h.thickness_mean_nm + h.thickness_std_nm); }
  if (hi <= lo) { hi = lo + 1; }
  const X = i => 50 + i * (c.width - 70) / Math.max(1, pts.length - 1);
  const Y = v => c.height - 30 - (v - lo) / (hi - lo) * (c.height - 50);
  g.fillStyle = 'rgba(33,145,140,0.25)'; g.beginPath();
  pts.forEach((h,i) => { const y = Y(h.thickness_mean_nm + h.thickness_std_nm); i ? g.lineTo(X(i), y) : g.moveTo(X(i), y); });
  for (let i = pts.length - 1; i >= 0; i--) g.lineTo(X(i), Y(pts[i].thickness_mean_nm - pts[i].thickness_std_nm));
  g.closePath(); g.fill();
  g.strokeStyle = '#440154'; g.lineWidth = 2; g.beginPath();
  pts.forEach((h,i) => { const y = Y(h.thickness_mean_nm); i ? g.lineTo(X(i), y) : g.moveTo(X(i), y); });
  g.stroke();
  g.fillStyle = '#000'; g.font = '12px sans-serif';
  g.fillText(hi.toFixed(1), 2, 24); g.fillText(lo.toFixed(1), 2, c.height - 30);
  g.fillText('sweep ' + pts[0].sweep + ' to ' + pts[pts.length-1].sweep, 50, c.height - 8);
  c.dataset.points = String(pts.length);
}
// One map request at a time: a new sweep never aborts a load in flight.
let loading = false, wanted = null;
const img = document.getElementById('map');
function loadMap(n){ wanted = n; if (loading) return; loading = true; img.src = '/map.png?sweep=' + n; }
// After a load, the newest sweep asked for meanwhile; after a failure (no
// map yet, a dropped connection), the same again half a second later.
img.onload = () => { img.dataset.loaded = String(img.naturalWidth); loading = false;
  if (!img.src.endsWith('sweep=' + wanted)) loadMap(wanted); };
img.onerror = () => { loading = false; setTimeout(() => loadMap(wanted), 500); };
function show(s){
  // A stream's first event repeats the newest summary the page has.
  if (hist.length && s.sweep <= hist[hist.length - 1].sweep) return;
  hist.push(s); if (hist.length > 600) hist.shift();
  document.getElementById('sweep').textContent = s.sweep;
  document.getElementById('valid').textContent = fmt(100 * s.valid_fraction, 1) + ' %';
  document.getElementById('drops').textContent = s.frames_dropped + ' frames / ' + s.sweeps_dropped + ' sweeps';
  document.getElementById('lat').textContent = fmt(s.latency_ms, 1) + ' ms';
  loadMap(s.sweep);
  draw();
}
// The trend so far comes inline, so that the page is drawn when it has
// loaded (its map is part of the load); then the events follow.
[/*HISTORY*/].forEach(show);
const es = new EventSource('/events'); es.onmessage = e => show(JSON.parse(e.data));
</script></body></html>
"##;
