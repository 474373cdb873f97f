//! Publishing to the plant over MQTT (rumqttc), without ever stalling the
//! line.
//!
//! [`MqttPublisher::publish`] only appends to a bounded queue (the oldest
//! message is dropped, and counted, when it is full). A worker thread owns
//! the MQTT connection and sends the queue's front with QoS 1, one message
//! in flight: a message leaves the queue only when the broker has
//! acknowledged it. When the broker goes away the worker retries every
//! `retry` and, once connected again, resends from the front: every
//! message still queued is delivered after the reconnect, in order (at
//! least once: a message whose acknowledgement was lost is sent again).
//!
//! (rumqttc's own queue is not enough: on a new session after a broker
//! restart it clears the requests it held.)

use super::output::Publisher;
use rumqttc::{Client, Connection, Event, MqttOptions, Packet, QoS};
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Counters of a publisher.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct MqttStats {
    /// Messages handed to the publisher.
    pub queued: u64,
    /// Messages acknowledged by the broker.
    pub delivered: u64,
    /// Messages dropped because the queue was full.
    pub dropped: u64,
    /// Connections made (1 + reconnects).
    pub connections: u64,
    /// Messages waiting now.
    pub waiting: u64,
}

/// Where to publish.
#[derive(Clone, Debug)]
pub struct MqttConfig {
    /// Broker host.
    pub host: String,
    /// Broker port.
    pub port: u16,
    /// Client id.
    pub client_id: String,
    /// Queue capacity, messages.
    pub capacity: usize,
    /// Wait between connection attempts.
    pub retry: Duration,
}

impl MqttConfig {
    /// `host:port` with defaults (client id `irid-line`, 1024 messages,
    /// retry every 200 ms).
    pub fn new(host: &str, port: u16) -> MqttConfig {
        MqttConfig {
            host: host.to_string(),
            port,
            client_id: "irid-line".into(),
            capacity: 1024,
            retry: Duration::from_millis(200),
        }
    }
}

struct Shared {
    queue: Mutex<VecDeque<(String, String)>>,
    wake: Condvar,
    stop: AtomicBool,
    queued: AtomicU64,
    delivered: AtomicU64,
    dropped: AtomicU64,
    connections: AtomicU64,
}

/// An MQTT publisher with a bounded queue and a worker thread.
pub struct MqttPublisher {
    shared: Arc<Shared>,
    capacity: usize,
    worker: Option<JoinHandle<()>>,
    flush_timeout: Duration,
}

impl MqttPublisher {
    /// Start the worker (it connects in the background: a broker that is
    /// not there yet is not an error).
    pub fn start(cfg: MqttConfig) -> MqttPublisher {
        let shared = Arc::new(Shared {
            queue: Mutex::new(VecDeque::with_capacity(cfg.capacity.max(1))),
            wake: Condvar::new(),
            stop: AtomicBool::new(false),
            queued: AtomicU64::new(0),
            delivered: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
            connections: AtomicU64::new(0),
        });
        let capacity = cfg.capacity.max(1);
        let s = shared.clone();
        let worker = std::thread::Builder::new()
            .name("irid-mqtt".into())
            .spawn(move || worker(cfg, s))
            .ok();
        MqttPublisher {
            shared,
            capacity,
            worker,
            flush_timeout: Duration::from_secs(5),
        }
    }

    /// How long [`Publisher::flush`] waits for the queue to drain.
    pub fn set_flush_timeout(&mut self, t: Duration) {
        self.flush_timeout = t;
    }

    /// The counters.
    pub fn stats(&self) -> MqttStats {
        let s = &self.shared;
        MqttStats {
            queued: s.queued.load(Ordering::Relaxed),
            delivered: s.delivered.load(Ordering::Relaxed),
            dropped: s.dropped.load(Ordering::Relaxed),
            connections: s.connections.load(Ordering::Relaxed),
            waiting: lock(&s.queue).len() as u64,
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Publisher for MqttPublisher {
    fn publish(&mut self, topic: &str, payload: &str) {
        let s = &self.shared;
        {
            let mut q = lock(&s.queue);
            if q.len() >= self.capacity {
                q.pop_front();
                s.dropped.fetch_add(1, Ordering::Relaxed);
            }
            q.push_back((topic.to_string(), payload.to_string()));
        }
        s.queued.fetch_add(1, Ordering::Relaxed);
        s.wake.notify_one();
    }

    fn flush(&mut self) {
        let end = Instant::now() + self.flush_timeout;
        while Instant::now() < end && !lock(&self.shared.queue).is_empty() {
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

impl Drop for MqttPublisher {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        self.shared.wake.notify_one();
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}

fn connect(cfg: &MqttConfig) -> (Client, Connection) {
    let mut o = MqttOptions::new(&cfg.client_id, &cfg.host, cfg.port);
    o.set_keep_alive(Duration::from_secs(5));
    o.set_clean_session(true);
    Client::new(o, 16)
}

/// The worker: keep one message in flight, the queue's front, until acked.
fn worker(cfg: MqttConfig, s: Arc<Shared>) {
    let (mut client, mut conn) = connect(&cfg);
    let mut connected = false;
    let mut in_flight = false;
    while !s.stop.load(Ordering::Relaxed) {
        if connected && !in_flight {
            let front = lock(&s.queue).front().cloned();
            if let Some((topic, payload)) = front {
                if client
                    .try_publish(topic, QoS::AtLeastOnce, false, payload)
                    .is_ok()
                {
                    in_flight = true;
                }
            } else {
                // Nothing to send: wait for a message, but keep polling
                // the connection (pings, broker loss).
                let q = lock(&s.queue);
                let _ = s.wake.wait_timeout(q, Duration::from_millis(20));
            }
        }
        match conn.recv_timeout(Duration::from_millis(50)) {
            Ok(Ok(Event::Incoming(Packet::ConnAck(_)))) => {
                connected = true;
                in_flight = false;
                s.connections.fetch_add(1, Ordering::Relaxed);
            }
            Ok(Ok(Event::Incoming(Packet::PubAck(_)))) => {
                if in_flight {
                    lock(&s.queue).pop_front();
                    s.delivered.fetch_add(1, Ordering::Relaxed);
                    in_flight = false;
                }
            }
            Ok(Ok(_)) => {}
            Ok(Err(e)) => {
                if connected {
                    tracing::warn!(%e, "MQTT broker lost; queueing");
                }
                connected = false;
                in_flight = false;
                std::thread::sleep(cfg.retry);
            }
            Err(rumqttc::RecvTimeoutError::Timeout) => {}
            Err(rumqttc::RecvTimeoutError::Disconnected) => {
                // The request channel closed: start a fresh client.
                (client, conn) = connect(&cfg);
                connected = false;
                in_flight = false;
            }
        }
    }
    let _ = client.disconnect();
}
