//! Per-method counters and latency percentiles (Stats, --metrics, slow-request log).

use graspd_proto::{self as proto, Method, StatusCode};

/// Answers kept for the percentiles, per method.
pub const WINDOW: usize = 4096;

#[derive(Clone)]
pub struct MethodCounters {
    pub requests: u64,
    pub by_status: [u64; 16],
    pub slow: u64,
    pub in_flight: u32,
    /// Ring buffers of the last WINDOW answers: server time and engine time, ns.
    server_ns: Vec<u64>,
    compute_ns: Vec<u64>,
    next: usize,
}

impl MethodCounters {
    fn new() -> Self {
        Self {
            requests: 0,
            by_status: [0; 16],
            slow: 0,
            in_flight: 0,
            server_ns: Vec::with_capacity(WINDOW),
            compute_ns: Vec::with_capacity(WINDOW),
            next: 0,
        }
    }
}

pub struct Stats {
    pub methods: Vec<MethodCounters>,
}

impl Default for Stats {
    fn default() -> Self {
        Self::new()
    }
}

/// Percentile (nearest rank) of sorted values; 0 when empty.
pub fn percentile_sorted(sorted: &[u64], q: f64) -> u64 {
    if sorted.is_empty() {
        return 0;
    }
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    sorted[rank - 1]
}

impl Stats {
    pub fn new() -> Self {
        Self { methods: Method::ALL.iter().map(|_| MethodCounters::new()).collect() }
    }

    /// Records an answer; returns true when it was slow.
    pub fn record(
        &mut self,
        method: Method,
        status: StatusCode,
        server_ns: u64,
        compute_ns: u64,
        slow_ns: u64,
    ) -> bool {
        let m = &mut self.methods[method as usize];
        m.requests += 1;
        m.by_status[(status as usize).min(15)] += 1;
        if m.server_ns.len() < WINDOW {
            m.server_ns.push(server_ns);
            m.compute_ns.push(compute_ns);
        } else {
            m.server_ns[m.next] = server_ns;
            m.compute_ns[m.next] = compute_ns;
        }
        m.next = (m.next + 1) % WINDOW;
        let slow = server_ns > slow_ns;
        m.slow += slow as u64;
        slow
    }

    pub fn to_wire(&self, uptime_ns: u64, rss_bytes: u64, clients: u64, queued: u32) -> proto::StatsResponse {
        let mut r = proto::StatsResponse::zeroed();
        r.uptime_ns = uptime_ns;
        r.rss_bytes = rss_bytes;
        r.clients_connected = clients;
        r.queued = queued;
        r.method_count = Method::ALL.len() as u32;
        for (i, method) in Method::ALL.iter().enumerate() {
            let m = &self.methods[i];
            let w = &mut r.methods[i];
            w.name = proto::str_to_text(method.name());
            w.requests = m.requests;
            w.by_status = m.by_status;
            w.slow = m.slow;
            w.in_flight = m.in_flight;
            w.window = m.server_ns.len() as u32;
            let mut s = m.server_ns.clone();
            s.sort_unstable();
            let mut c = m.compute_ns.clone();
            c.sort_unstable();
            let us = |v: u64| v as f64 * 1e-3;
            w.latency_p50_us = us(percentile_sorted(&s, 0.5));
            w.latency_p90_us = us(percentile_sorted(&s, 0.9));
            w.latency_p99_us = us(percentile_sorted(&s, 0.99));
            w.latency_max_us = us(s.last().copied().unwrap_or(0));
            w.compute_p50_us = us(percentile_sorted(&c, 0.5));
            w.compute_p99_us = us(percentile_sorted(&c, 0.99));
        }
        r
    }
}

/// The process's resident set size, bytes (Linux; 0 elsewhere).
pub fn rss_bytes() -> u64 {
    let Ok(s) = std::fs::read_to_string("/proc/self/statm") else { return 0 };
    let pages: u64 = s.split_whitespace().nth(1).and_then(|v| v.parse().ok()).unwrap_or(0);
    pages * 4096
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_over_a_rolling_window() {
        let mut s = Stats::new();
        for i in 1..=100u64 {
            s.record(Method::Register, StatusCode::Ok, i * 1000, i * 500, 95_000);
        }
        s.record(Method::Register, StatusCode::InvalidArgument, 1000, 0, 95_000);
        let w = s.to_wire(1, 2, 3, 0);
        let m = &w.methods[Method::Register as usize];
        assert_eq!(m.requests, 101);
        assert_eq!(m.by_status[0], 100);
        assert_eq!(m.by_status[3], 1);
        assert_eq!(m.slow, 5);
        assert_eq!(m.latency_max_us, 100.0);
        assert_eq!(m.latency_p50_us, 50.0);
        for _ in 0..2 * WINDOW {
            s.record(Method::Health, StatusCode::Ok, 7, 0, 1_000_000);
        }
        let w = s.to_wire(1, 2, 3, 0);
        assert_eq!(w.methods[0].window as usize, WINDOW);
        assert_eq!(w.methods[0].latency_max_us, 0.007);
    }
}
