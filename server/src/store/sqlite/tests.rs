//! What only the SQLite store does: its file, its lock file, its backup,
//! and what it makes of a file edited by hand. (What every engine does is
//! in `store::suite`.)

use std::sync::Arc;

use sqlx::Connection;

use super::*;
use crate::domain::{MissionRecord, Timestamp};
use crate::store::Store;
use crate::store::suite::{HASH, robot_spec, spec};
use crate::store::{Changeset, LoggedPatch, compact};
use exploration::fusion::Patch;
use exploration::grid::CellRect;

/// A store in the new file `path`, holding one mission of [`spec`].
pub(super) async fn store_with_mission(path: &std::path::Path, durability: Durability) -> (SqliteStore, MissionRecord) {
    let store = SqliteStore::open(path, durability).await.unwrap();
    let mission = store.create_mission(&spec(), Timestamp(1)).await.unwrap();
    (store, mission)
}

/// A database holding one mission with one robot, one patch folded into
/// its map snapshot and one after it, closed again; returns the file.
async fn stored_mission(dir: &std::path::Path) -> std::path::PathBuf {
    let path = dir.join("s.db");
    let store = SqliteStore::open(&path, Durability::Full).await.unwrap();
    let mission = store.create_mission(&spec(), Timestamp(1)).await.unwrap();
    let robot =
        store.create_robot(mission.id, &robot_spec("r1"), &|_| HASH.to_owned(), Timestamp(1), None).await.unwrap();
    for seq in 1..=2 {
        let patch = Patch::from_probabilities(CellRect::new(1, 1, 2, 1), &[0.2, 0.9], &[]).unwrap();
        let changes = Changeset {
            patches: vec![LoggedPatch { robot_id: robot.id, seq, patch: Arc::new(patch) }],
            ..Changeset::default()
        };
        store.commit(changes).await.unwrap();
    }
    assert_eq!(compact::fold(&store, &mission, 1).await.unwrap(), 1);
    store.close().await;
    drop(store);
    path
}

/// Every value read back is checked like input from the network: a bad row
/// stops the start with the table, the row and the column, never a panic, a
/// wrap-around or an allocation sized by the row.
#[tokio::test]
async fn corrupt_rows_are_refused_naming_table_row_and_column() {
    let cases = [
        ("UPDATE missions SET replan_interval_s = -1", "missions row 1: replan_interval_s"),
        ("UPDATE missions SET lease_s = 1e300", "missions row 1: lease_s"),
        ("UPDATE missions SET width = 4294967297", "missions row 1: width"),
        ("UPDATE missions SET width = 20000, height = 20000", "missions row 1: width × height"),
        ("UPDATE missions SET origin_x = 1e308", "missions row 1: origin.x"),
        ("UPDATE missions SET policy_params = '{\"beta\": -5}'", "missions row 1"),
        ("UPDATE missions SET state = 'exploded'", "missions row 1: state"),
        ("UPDATE missions SET name = 'a' || char(10) || 'b'", "missions row 1: name"),
        ("UPDATE robots SET pose_x = 1e9", "robots row 1: (pose_x, pose_y)"),
        ("UPDATE robots SET speed_mps = 0", "robots row 1: speed_mps"),
        ("UPDATE robots SET last_map_seq = -4", "robots row 1: last_map_seq"),
        ("UPDATE map_patches SET width = 4000000000", "map_patches row 2"),
        ("UPDATE map_patches SET cells = x'00'", "map_patches row 2: cells"),
        ("UPDATE map_patches SET cells = x'ffffffff'", "map_patches row 2: cells"),
        ("UPDATE map_patches SET cells_format = 7", "map_patches row 2: cells_format 7"),
        ("UPDATE map_patches SET cells_format = 0, cells = x'00'", "map_patches row 2: cells holds 1 bytes"),
        ("UPDATE map_patches SET cells_format = 0, cells = x'0000807f0000807f'", "map_patches row 2"),
        // Two cells as occupancy bytes, one LZ4 block of literals each: one
        // byte short, and a byte that is no percentage.
        ("UPDATE map_patches SET cells_format = 2, cells = x'1005'", "map_patches row 2: cells holds 1 bytes"),
        (
            "UPDATE map_patches SET cells_format = 2, cells = x'200565'",
            "map_patches row 2: occupancy byte 1 of the patch is 101",
        ),
        ("UPDATE map_snapshots SET state = x'00'", "map_snapshots: the snapshot"),
        ("UPDATE map_snapshots SET raw_bytes = 1000000000000", "map_snapshots: the snapshot claims"),
        ("UPDATE map_snapshots SET folded = -1", "map_snapshots row 1: folded"),
        ("UPDATE map_snapshots SET through_patch_id = 0", "map_snapshots row 1: through_patch_id"),
    ];
    for (edit, expected) in cases {
        let dir = tempfile::tempdir().unwrap();
        let path = stored_mission(dir.path()).await;
        let mut raw = sqlx::SqliteConnection::connect(&format!("sqlite:{}", path.display())).await.unwrap();
        // An edit by hand need not respect the schema's checks either.
        sqlx::query("PRAGMA ignore_check_constraints = ON").execute(&mut raw).await.unwrap();
        sqlx::query(edit).execute(&mut raw).await.unwrap();
        raw.close().await.unwrap();
        let store = SqliteStore::open(&path, Durability::Full).await.unwrap();
        // What the executive reads at start: missions, then each one's robots and patches.
        let read = async {
            for mission in store.missions().await? {
                store.robots(&mission).await?;
                let robots = store.robots(&mission).await?.len();
                store.stored_map(&mission, None).await?.fuse(&mission.spec.frame, robots)?;
            }
            Ok::<_, StoreError>(())
        };
        let err = read.await.expect_err(edit).to_string();
        assert!(err.contains(expected), "{edit}: {err}");
    }
}

/// Only a file keeps what is acknowledged: in-memory databases, folders,
/// devices and files in missing folders are refused with the reason, before
/// a lock file is made beside them.
#[tokio::test]
async fn only_database_files_are_opened() {
    let dir = tempfile::tempdir().unwrap();
    for (path, why) in [
        (std::path::PathBuf::from(":memory:"), "database file"),
        (std::path::PathBuf::from("file:x?mode=memory"), "database file"),
        (dir.path().to_owned(), "is a folder"),
        (dir.path().join("missing/x.db"), "does not exist"),
        (std::path::PathBuf::from("/dev/null"), "is not a regular file"),
    ] {
        let err = SqliteStore::open(&path, Durability::Full).await.unwrap_err();
        assert!(matches!(err, StoreError::Path(_)) && err.to_string().contains(why), "{path:?}: {err}");
    }
    assert!(!std::path::Path::new("/dev/null.lock").exists(), "a lock file was made in /dev");
}

/// A backup taken while the store is open holds everything committed, and
/// opens as a store of its own.
#[tokio::test]
async fn a_backup_is_a_consistent_store() {
    let dir = tempfile::tempdir().unwrap();
    let path = stored_mission(dir.path()).await;
    let store = SqliteStore::open(&path, Durability::Full).await.unwrap();
    let copy = dir.path().join("copy.db");
    store.backup(&copy).await.unwrap();
    assert!(store.backup(&copy).await.is_err(), "an existing file is never overwritten");
    let restored = SqliteStore::open(&copy, Durability::Full).await.unwrap();
    let missions = restored.missions().await.unwrap();
    assert_eq!(missions, store.missions().await.unwrap());
    assert_eq!(restored.stored_map(&missions[0], None).await.unwrap().patches.len(), 1);
}
