//! `#[derive(pulicast::Schema)]` gives the schema (and so the fingerprint
//! and the announced description) that postcard-schema's own derive gives.
//! That it needs no postcard-schema dependency is shown by `examples/`,
//! which has none.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use pulicast_proto::wire::{fingerprint_of, type_info_of};
use serde::{Deserialize, Serialize};

/// The same types, derived with `$derive`.
macro_rules! message_types {
    ($derive:path) => {
        #[derive(Serialize, Deserialize, $derive)]
        pub struct Twist {
            pub linear: f64,
            pub angular: f64,
        }

        #[derive(Serialize, Deserialize, $derive)]
        #[serde(rename = "Pose2")]
        pub struct Pose(pub f32, pub f32);

        #[derive(Serialize, Deserialize, $derive)]
        pub enum Mode {
            Idle,
            #[serde(rename = "go")]
            Drive {
                speed: f64,
            },
            Turn(i16),
        }

        #[derive(Serialize, Deserialize, $derive)]
        pub struct Stamped<T> {
            pub stamp: u64,
            pub value: T,
        }

        // postcard-schema stops reading at `rename_all`: the name stays.
        #[derive(Serialize, Deserialize, $derive)]
        #[serde(rename_all = "camelCase", rename = "Odo2")]
        pub struct Odometry {
            pub total_distance: f64,
        }

        #[derive(Serialize, Deserialize, $derive)]
        #[serde(rename = "Odo3", rename_all = "camelCase")]
        pub struct Odometer {
            pub total_distance: f64,
        }

        #[derive(Serialize, Deserialize, $derive, Clone, Copy)]
        #[repr(u8)]
        pub enum Command {
            Stop = 0,
            Go = 7,
        }
    };
}

/// Each type twice: through pulicast, and through postcard-schema directly.
mod ours {
    use super::*;
    message_types!(pulicast::Schema);
}

mod theirs {
    use super::*;
    message_types!(postcard_schema::Schema);
}

fn same<A: postcard_schema::Schema, B: postcard_schema::Schema>() {
    assert_eq!(fingerprint_of::<A>(), fingerprint_of::<B>());
    let (a, b) = (type_info_of::<A>(), type_info_of::<B>());
    assert_eq!((a.name, a.schema), (b.name, b.schema));
}

#[test]
fn the_derive_gives_postcard_schemas_own_schema() {
    same::<ours::Twist, theirs::Twist>();
    same::<ours::Pose, theirs::Pose>();
    same::<ours::Mode, theirs::Mode>();
    same::<ours::Stamped<ours::Twist>, theirs::Stamped<theirs::Twist>>();
    same::<ours::Odometry, theirs::Odometry>();
    same::<ours::Odometer, theirs::Odometer>();
    same::<ours::Command, theirs::Command>();
    assert_eq!(type_info_of::<ours::Odometry>().name, "Odometry");
    assert_eq!(type_info_of::<ours::Odometer>().name, "Odo3");
    // A type defined in a function body.
    #[derive(Serialize, Deserialize, pulicast::Schema)]
    struct Local {
        inner: ours::Twist,
    }
    assert_eq!(type_info_of::<Local>().name, "Local");
    assert_eq!(type_info_of::<ours::Twist>().name, "Twist");
    assert_eq!(type_info_of::<ours::Pose>().name, "Pose2");
}

#[test]
fn a_derived_type_goes_through_a_node_unchanged() {
    let mut bytes = Vec::new();
    let value = ours::Stamped {
        stamp: 7,
        value: ours::Twist {
            linear: 0.3,
            angular: -1.0,
        },
    };
    pulicast_proto::wire::encode_native(&value, &mut bytes).unwrap();
    let back: ours::Stamped<ours::Twist> = pulicast_proto::wire::decode_native(&bytes).unwrap();
    assert_eq!(
        (back.stamp, back.value.linear, back.value.angular),
        (7, 0.3, -1.0)
    );
}
