//! The JSON form of the Stats body, one shape for every reader: the
//! daemon's `--metrics` log line and `graspctl stats --json`. Behind the
//! `json` feature, so that a client that only calls methods does not link
//! serde_json.

use crate::{text_lossy, StatsResponse, StatusCode, MAX_METHODS};
use serde_json::{json, Map, Value};

/// `{uptime_s, rss_bytes, clients_connected, queued, methods: [{method,
/// requests, errors, by_status, slow, in_flight, latency_us, compute_us}]}`;
/// `by_status` names only the codes that occurred, `errors` counts every
/// answer but OK.
pub fn stats_json(s: &StatsResponse) -> Value {
    let methods: Vec<Value> = s.methods[..(s.method_count as usize).min(MAX_METHODS)]
        .iter()
        .map(|m| {
            let by_status: Map<String, Value> = StatusCode::ALL
                .iter()
                .filter(|c| m.by_status[**c as usize] > 0)
                .map(|c| (c.name().to_owned(), json!(m.by_status[*c as usize])))
                .collect();
            json!({
                "method": text_lossy(&m.name),
                "requests": m.requests,
                "errors": m.requests.saturating_sub(m.by_status[StatusCode::Ok as usize]),
                "by_status": by_status,
                "slow": m.slow,
                "in_flight": m.in_flight,
                "latency_us": {"p50": m.latency_p50_us, "p90": m.latency_p90_us, "p99": m.latency_p99_us, "max": m.latency_max_us, "window": m.window},
                "compute_us": {"p50": m.compute_p50_us, "p99": m.compute_p99_us},
            })
        })
        .collect();
    json!({
        "uptime_s": s.uptime_ns as f64 * 1e-9,
        "rss_bytes": s.rss_bytes,
        "clients_connected": s.clients_connected,
        "queued": s.queued,
        "methods": methods,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Plain;

    #[test]
    fn counts_every_answer_but_ok_as_an_error_and_names_only_the_codes_seen() {
        let mut s = StatsResponse::from_bytes(&vec![0u8; core::mem::size_of::<StatsResponse>()]).unwrap();
        s.method_count = 1;
        s.methods[0].name[..8].copy_from_slice(b"register");
        s.methods[0].requests = 7;
        s.methods[0].by_status[StatusCode::Ok as usize] = 4;
        s.methods[0].by_status[StatusCode::InvalidArgument as usize] = 3;
        let v = stats_json(&s);
        let m = &v["methods"][0];
        assert_eq!(m["method"], "register");
        assert_eq!(m["errors"], 3);
        assert_eq!(m["by_status"], json!({"OK": 4, "INVALID_ARGUMENT": 3}));
        // A method count beyond the array (a garbled body) is clamped, not a panic.
        s.method_count = u32::MAX;
        assert_eq!(stats_json(&s)["methods"].as_array().unwrap().len(), MAX_METHODS);
    }
}
