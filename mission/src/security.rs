//! Zenoh security for a mission: who may connect (user/password, optionally mutual TLS) and
//! what each may do (access control on the router, default deny). A vehicle may put only under
//! `vehicle/<its id>/`, query only `plan/<its id>`, subscribe only to its acks, its ground-station
//! frames and `model/latest`; the ground-station gateway carries MAVLink frames; an observer
//! reads the model and the server's status; only the server (the router itself) puts models,
//! plans and acks. `fleet secure` writes these files.

use crate::config::MissionConfig;
use crate::protocol::keys::Keys;
use crate::protocol::ProtocolError;
use serde_json::{json, Value};

/// Users besides the vehicles.
pub const GATEWAY: &str = "gcs-gateway";
pub const OBSERVER: &str = "observer";

/// Where the certificates are (from `scripts/make-test-ca.sh` or your own CA): `ca.pem`, and
/// `<name>.pem` / `<name>.key` for the server and each user, whose common name is the name.
#[derive(Debug, Clone)]
pub struct Tls {
    pub dir: std::path::PathBuf,
}

impl Tls {
    fn file(&self, name: &str) -> String {
        self.dir.join(name).display().to_string()
    }
}

fn rule(id: &str, flow: &str, messages: &[&str], keys: &[String]) -> Value {
    json!({ "id": id, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": keys })
}

/// The access-control section of the router's config. Every key pattern comes from
/// [`Keys`], the one definition of the key space (a key renamed there is renamed here).
///
/// Long because it is one document: the ACL as Zenoh reads it, rules, subjects and policies
/// together.
pub fn access_control(mission: &MissionConfig, tls: bool) -> Result<Value, ProtocolError> {
    let k = Keys::new(&mission.mission)?;
    let mut rules = vec![];
    let mut subjects = vec![];
    let mut policies = vec![];
    let mut add = |user: &str, user_rules: Vec<Value>| {
        let ids: Vec<Value> = user_rules.iter().map(|r| r["id"].clone()).collect();
        rules.extend(user_rules);
        let mut subject = json!({ "id": user, "usernames": [user] });
        if tls {
            subject["cert_common_names"] = json!([user]);
        }
        subjects.push(subject);
        policies.push(json!({ "id": user, "rules": ids, "subjects": [user] }));
    };
    // Every authenticated node learns where subscribers and queryables are (declarations only,
    // no data), so its puts and queries are routed at all.
    let declarations = |user: &str| {
        rule(
            &format!("{user}/declarations"),
            "egress",
            &["declare_subscriber", "declare_queryable"],
            &[k.everything()],
        )
    };
    let server = k.alive("server");
    for v in mission.vehicles() {
        let id = v.id.as_str();
        let inbound = vec![k.ack(id), k.gcs(id), k.model_latest()];
        add(
            id,
            vec![
                rule(
                    &format!("{id}/put"),
                    "ingress",
                    &["put"],
                    &[k.measurements(id), k.telemetry(id), k.mavlink(id)],
                ),
                rule(&format!("{id}/subscribe"), "ingress", &["declare_subscriber"], &inbound),
                rule(&format!("{id}/receive"), "egress", &["put"], &inbound),
                rule(&format!("{id}/ask-plan"), "ingress", &["query"], &[k.plan(id)]),
                rule(&format!("{id}/get-plan"), "egress", &["reply"], &[k.plan(id)]),
                rule(&format!("{id}/token"), "ingress", &["liveliness_token"], &[k.alive(id)]),
                rule(
                    &format!("{id}/watch-server"),
                    "ingress",
                    &["declare_liveliness_subscriber", "liveliness_query"],
                    std::slice::from_ref(&server),
                ),
                rule(
                    &format!("{id}/server-alive"),
                    "egress",
                    &["liveliness_token", "reply"],
                    std::slice::from_ref(&server),
                ),
                declarations(id),
            ],
        );
    }
    add(
        GATEWAY,
        vec![
            rule(
                "gcs-gateway/subscribe",
                "ingress",
                &["declare_subscriber"],
                &[k.all_mavlink(), k.server_status()],
            ),
            rule(
                "gcs-gateway/receive",
                "egress",
                &["put"],
                &[k.all_mavlink(), k.server_status()],
            ),
            // The operator's commands: frames to the autopilots, verdicts on sensors.
            rule(
                "gcs-gateway/put",
                "ingress",
                &["put"],
                &[k.all_gcs(), k.all_sensor_overrides()],
            ),
            rule(
                "gcs-gateway/token",
                "ingress",
                &["liveliness_token"],
                &[k.alive(GATEWAY)],
            ),
            declarations(GATEWAY),
        ],
    );
    // The observer (the live view): the model, the server's status, every vehicle's
    // telemetry and plans; it puts nothing.
    let seen = vec![k.model_latest(), k.server_status(), k.telemetry("*")];
    add(
        OBSERVER,
        vec![
            rule(
                "observer/ask-model",
                "ingress",
                &["query"],
                &[k.model_latest(), k.all_plans()],
            ),
            rule(
                "observer/get-model",
                "egress",
                &["reply"],
                &[k.model_latest(), k.all_plans()],
            ),
            rule("observer/subscribe", "ingress", &["declare_subscriber"], &seen),
            rule("observer/receive", "egress", &["put"], &seen),
            rule(
                "observer/watch-links",
                "ingress",
                &["declare_liveliness_subscriber", "liveliness_query"],
                &[k.all_alive()],
            ),
            rule(
                "observer/links",
                "egress",
                &["liveliness_token", "reply"],
                &[k.all_alive()],
            ),
            declarations(OBSERVER),
        ],
    );
    Ok(json!({
        "enabled": true, "default_permission": "deny",
        "rules": rules, "subjects": subjects, "policies": policies
    }))
}

/// Every user of the mission: the vehicles, the gateway and the observer.
pub fn users(mission: &MissionConfig) -> Vec<String> {
    let mut u: Vec<String> = mission.vehicles().into_iter().map(|v| v.id.into()).collect();
    u.extend([GATEWAY.to_string(), OBSERVER.to_string()]);
    u
}

/// Endpoints with `tcp/` turned into `tls/` when TLS is on.
fn endpoints(list: &[String], tls: bool) -> Vec<String> {
    list.iter()
        .map(|e| if tls { e.replacen("tcp/", "tls/", 1) } else { e.clone() })
        .collect()
}

/// The router's (model server's) config: listen, the password dictionary, TLS, access control.
pub fn router_config(
    mission: &MissionConfig,
    dictionary: &std::path::Path,
    tls: Option<&Tls>,
) -> Result<Value, ProtocolError> {
    let mut c = json!({
        "mode": "router",
        "listen": { "endpoints": endpoints(&mission.network.listen, tls.is_some()) },
        "scouting": { "multicast": { "enabled": false } },
        "transport": { "auth": { "usrpwd": { "dictionary_file": dictionary.display().to_string() } } },
        "access_control": access_control(mission, tls.is_some())?,
    });
    if let Some(t) = tls {
        c["transport"]["link"] = json!({ "tls": {
            "root_ca_certificate": t.file("ca.pem"),
            "listen_certificate": t.file("server.pem"),
            "listen_private_key": t.file("server.key"),
            "enable_mtls": true,
        }});
    }
    Ok(c)
}

/// One user's client config: where the router is, its credentials and certificate.
pub fn client_config(mission: &MissionConfig, user: &str, password: &str, tls: Option<&Tls>) -> Value {
    let mut c = json!({
        "mode": "client",
        "connect": { "endpoints": endpoints(&mission.network.connect, tls.is_some()) },
        "scouting": { "multicast": { "enabled": false } },
        "transport": { "auth": { "usrpwd": { "user": user, "password": password } } },
    });
    if let Some(t) = tls {
        c["transport"]["link"] = json!({ "tls": {
            "root_ca_certificate": t.file("ca.pem"),
            "connect_certificate": t.file(&format!("{user}.pem")),
            "connect_private_key": t.file(&format!("{user}.key")),
            "enable_mtls": true,
        }});
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_vehicle_may_put_only_under_its_own_key() {
        let m = MissionConfig::load(None).unwrap();
        let acl = access_control(&m, false).unwrap();
        let puts: Vec<&Value> = acl["rules"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|r| r["id"] == "boat-1/put")
            .collect();
        assert_eq!(puts.len(), 1);
        for key in puts[0]["key_exprs"].as_array().unwrap() {
            assert!(
                key.as_str().unwrap().starts_with("fleet/default/vehicle/boat-1/"),
                "{key}"
            );
        }
        // Nobody but the router puts models, plans or acks: no ingress put rule names them.
        for r in acl["rules"].as_array().unwrap() {
            if r["flows"][0] == "ingress" && r["messages"].as_array().unwrap().contains(&json!("put")) {
                for key in r["key_exprs"].as_array().unwrap() {
                    let k = key.as_str().unwrap();
                    assert!(
                        !k.contains("/model/") && !k.contains("/plan/") && !k.ends_with("/ack"),
                        "{k}"
                    );
                }
            }
        }
        assert_eq!(acl["default_permission"], "deny");
        assert_eq!(acl["subjects"].as_array().unwrap().len(), users(&m).len());
    }
}
