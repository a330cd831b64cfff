//! The UR5's shoulder, upper arm and forearm as a serial chain of rigid bodies: forward
//! kinematics, the mass matrix (composite rigid body algorithm) and inverse dynamics (recursive
//! Newton-Euler), all on fixed-size nalgebra types so that nothing allocates.
//!
//! Frames follow the MuJoCo model the reference simulated (docs/ENVIRONMENTS.md): each body sits
//! at an offset in its parent's frame, turned by a fixed rotation, and its hinge turns it about an
//! axis of its own frame through its origin. The world frame is the fixed base's, z up.
//!
//! Inertia: the figures are MuJoCo's `<inertial pos=.. mass=.. diaginertia=..>`, and MuJoCo reads
//! `diaginertia` as the principal moments about the centre of mass, in an inertial frame at `pos`
//! whose axes are the body's (the model gives no inertial `quat`). That is how they are used here;
//! the parallel-axis theorem moves them wherever an algorithm needs them. For the shoulder the
//! centre of mass is the body origin, so "at its origin" and "about the centre of mass" agree.
//!
//! Everything below works in world coordinates. Joint torques follow
//!
//! ```text
//! M(q) qddot + C(q, qdot) qdot + g(q) = tau,      g(q) = dV/dq,   V = sum_i m_i g z_com_i.
//! ```

use nalgebra::{Matrix3, Quaternion, Rotation3, Unit, UnitQuaternion, Vector3};

/// Number of hinges (and moving bodies) in the chain.
pub const JOINTS: usize = 3;

/// Height of the shoulder pan joint above the base, m.
const SHOULDER_HEIGHT: f64 = 0.089159;

/// The upper arm's orientation in the shoulder's frame (w, x, y, z), 90 degrees about y.
#[expect(
    clippy::approx_constant,
    reason = "the MuJoCo model's digits, normalised where used"
)]
const UPPER_ARM_QUATERNION: [f64; 4] = [0.707107, 0.0, 0.707107, 0.0];

/// The wrist point of the goal rule (docs/ENVIRONMENTS.md) in the forearm's frame (the UR5's
/// wrist-1 joint).
///
/// The reference writes it as (0.39225, -0.1197, 0) in its own forward kinematics, whose frames
/// run x along the links (it leaves out the upper arm's quaternion) and which applies the
/// forearm's lateral offset of -0.1197 m at the wrist instead of at the elbow. In this chain's
/// frames (z along the links, the offset already in the forearm's origin) the same point is
/// (0, 0, 0.39225): the two agree in all three world coordinates for every q (tested).
pub const WRIST_IN_FOREARM: Vector3<f64> = Vector3::new(0.0, 0.0, 0.39225);

/// One rigid body of the chain with the hinge that carries it.
#[derive(Debug, Clone, Copy)]
struct Body {
    /// The body's origin (its hinge) in the parent's frame, m.
    offset: Vector3<f64>,
    /// The body's orientation in the parent's frame at zero joint angle.
    rotation: Matrix3<f64>,
    /// Hinge axis in the body's own frame.
    axis: Unit<Vector3<f64>>,
    /// kg.
    mass: f64,
    /// Centre of mass in the body's frame, m.
    com: Vector3<f64>,
    /// Rotational inertia about the centre of mass in the body's axes, kg m^2.
    inertia: Matrix3<f64>,
}

/// The three moving bodies of the ur5-reacher chain under a given gravity.
#[derive(Debug, Clone)]
pub struct Ur5Arm {
    bodies: [Body; JOINTS],
    gravity: f64,
}

/// Where every body of the arm is for one configuration q, in world coordinates. Computed once
/// per physics step and shared by the mass matrix and the inverse dynamics.
#[derive(Debug, Clone, Copy)]
pub struct Pose {
    rotation: [Matrix3<f64>; JOINTS],
    origin: [Vector3<f64>; JOINTS],
    axis: [Vector3<f64>; JOINTS],
    com: [Vector3<f64>; JOINTS],
    /// About each body's centre of mass, world axes.
    inertia: [Matrix3<f64>; JOINTS],
}

impl Pose {
    /// Origin (hinge position) of body `i` (0 shoulder, 1 upper arm, 2 forearm).
    pub fn origin(&self, i: usize) -> Vector3<f64> {
        self.origin[i]
    }

    /// Hinge axis of joint `i`, a unit vector.
    pub fn axis(&self, i: usize) -> Vector3<f64> {
        self.axis[i]
    }

    /// Centre of mass of body `i`.
    pub fn com(&self, i: usize) -> Vector3<f64> {
        self.com[i]
    }

    /// The world position of `local`, a point fixed in body `i`'s frame.
    pub fn point(&self, i: usize, local: &Vector3<f64>) -> Vector3<f64> {
        self.origin[i] + self.rotation[i] * local
    }

    /// Height of the elbow (the forearm's origin), m.
    pub fn elbow_height(&self) -> f64 {
        self.origin[2].z
    }

    /// Height of the wrist point [`WRIST_IN_FOREARM`], m.
    pub fn wrist_height(&self) -> f64 {
        self.point(2, &WRIST_IN_FOREARM).z
    }
}

impl Ur5Arm {
    /// The chain under gravity `gravity` (m/s^2, along -z).
    pub fn new(gravity: f64) -> Self {
        let hinge = |axis, mass, com, inertia: [f64; 3]| Body {
            offset: Vector3::zeros(),
            rotation: Matrix3::identity(),
            axis,
            mass,
            com,
            inertia: Matrix3::from_diagonal(&Vector3::from(inertia)),
        };
        // MuJoCo normalises quaternions; so does `from_quaternion`. The result turns the upper
        // arm's z axis onto the shoulder's x axis.
        let [w, x, y, z] = UPPER_ARM_QUATERNION;
        let upper_arm_rotation = UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z))
            .to_rotation_matrix()
            .into_inner();
        let shoulder = Body {
            offset: Vector3::new(0.0, 0.0, SHOULDER_HEIGHT),
            ..hinge(
                Vector3::z_axis(),
                3.7,
                Vector3::zeros(),
                [0.0102675, 0.0102675, 0.00666],
            )
        };
        let upper_arm = Body {
            offset: Vector3::new(0.0, 0.13585, 0.0),
            rotation: upper_arm_rotation,
            ..hinge(
                Vector3::y_axis(),
                8.393,
                Vector3::new(0.0, 0.0, 0.28),
                [0.226891, 0.226891, 0.0151074],
            )
        };
        let forearm = Body {
            offset: Vector3::new(0.0, -0.1197, 0.425),
            ..hinge(
                Vector3::y_axis(),
                2.275,
                Vector3::new(0.0, 0.0, 0.25),
                [0.0494433, 0.0494433, 0.004095],
            )
        };
        Self {
            bodies: [shoulder, upper_arm, forearm],
            gravity,
        }
    }

    /// Gravitational acceleration along -z, m/s^2.
    pub fn gravity(&self) -> f64 {
        self.gravity
    }

    /// Mass of body `i`, kg.
    pub fn mass(&self, i: usize) -> f64 {
        self.bodies[i].mass
    }

    /// Forward kinematics: every body's frame, axis, centre of mass and inertia for angles `q`.
    pub fn pose(&self, q: &Vector3<f64>) -> Pose {
        let mut rotation = Matrix3::identity();
        let mut origin = Vector3::zeros();
        let mut pose = Pose {
            rotation: [Matrix3::zeros(); JOINTS],
            origin: [Vector3::zeros(); JOINTS],
            axis: [Vector3::zeros(); JOINTS],
            com: [Vector3::zeros(); JOINTS],
            inertia: [Matrix3::zeros(); JOINTS],
        };
        for (i, body) in self.bodies.iter().enumerate() {
            // The hinge sits at the body's origin, so the parent's rotation places it and the
            // joint angle only turns what comes after.
            origin += rotation * body.offset;
            let joint = Rotation3::from_axis_angle(&body.axis, q[i]).into_inner();
            rotation = rotation * body.rotation * joint;
            pose.rotation[i] = rotation;
            pose.origin[i] = origin;
            pose.axis[i] = rotation * body.axis.into_inner();
            pose.com[i] = origin + rotation * body.com;
            pose.inertia[i] = rotation * body.inertia * rotation.transpose();
        }
        pose
    }

    /// The joint-space mass matrix M(q) by the composite rigid body algorithm.
    ///
    /// From the tip inwards, the bodies beyond joint i are lumped into one composite body (mass,
    /// centre of mass, inertia about that centre). With the arm at rest and only joint i
    /// accelerating at 1 rad/s^2 the composite turns rigidly about axis i; the wrench that
    /// motion needs, projected on the axis of every joint j <= i, is column i of M.
    pub fn mass_matrix(&self, pose: &Pose) -> Matrix3<f64> {
        let mut m = Matrix3::zeros();
        let mut mass = 0.0;
        let mut com = Vector3::zeros();
        let mut inertia = Matrix3::zeros();
        for i in (0..JOINTS).rev() {
            let body = &self.bodies[i];
            let merged_mass = mass + body.mass;
            let merged_com = (mass * com + body.mass * pose.com[i]) / merged_mass;
            inertia += point_inertia(mass, &(com - merged_com))
                + pose.inertia[i]
                + point_inertia(body.mass, &(pose.com[i] - merged_com));
            mass = merged_mass;
            com = merged_com;

            let z = pose.axis[i];
            let force = mass * z.cross(&(com - pose.origin[i]));
            let moment_about_com = inertia * z;
            for j in 0..=i {
                let moment = moment_about_com + (com - pose.origin[j]).cross(&force);
                let entry = pose.axis[j].dot(&moment);
                m[(j, i)] = entry;
                m[(i, j)] = entry;
            }
        }
        m
    }

    /// Inverse dynamics by recursive Newton-Euler: the joint torques that produce accelerations
    /// `qdd` at velocities `qd`, i.e. `M qdd + C qd + g`.
    ///
    /// Gravity enters as an upward acceleration of the base, which loads every body exactly as
    /// gravity does.
    pub fn inverse_dynamics(
        &self,
        pose: &Pose,
        qd: &Vector3<f64>,
        qdd: &Vector3<f64>,
    ) -> Vector3<f64> {
        // Outward: each body's angular velocity and acceleration, and the acceleration of its
        // origin; from those the force and moment (about its centre of mass) it needs.
        let mut omega = Vector3::zeros();
        let mut alpha = Vector3::zeros();
        let mut accel = Vector3::new(0.0, 0.0, self.gravity);
        let mut previous_origin = Vector3::zeros();
        let mut force = [Vector3::zeros(); JOINTS];
        let mut moment = [Vector3::zeros(); JOINTS];
        for (i, body) in self.bodies.iter().enumerate() {
            let hop = pose.origin[i] - previous_origin;
            accel += alpha.cross(&hop) + omega.cross(&omega.cross(&hop));
            let spin = pose.axis[i] * qd[i];
            alpha += pose.axis[i] * qdd[i] + omega.cross(&spin);
            omega += spin;
            let arm = pose.com[i] - pose.origin[i];
            let accel_com = accel + alpha.cross(&arm) + omega.cross(&omega.cross(&arm));
            force[i] = body.mass * accel_com;
            moment[i] = pose.inertia[i] * alpha + omega.cross(&(pose.inertia[i] * omega));
            previous_origin = pose.origin[i];
        }

        // Inward: the wrench each joint transmits carries its own body and everything beyond;
        // the joint supplies its component along the hinge axis.
        let mut tau = Vector3::zeros();
        let mut joint_force = Vector3::zeros();
        let mut joint_moment = Vector3::zeros();
        for i in (0..JOINTS).rev() {
            let child_moment = if i + 1 < JOINTS {
                joint_moment + (pose.origin[i + 1] - pose.origin[i]).cross(&joint_force)
            } else {
                Vector3::zeros()
            };
            joint_moment =
                moment[i] + (pose.com[i] - pose.origin[i]).cross(&force[i]) + child_moment;
            joint_force += force[i];
            tau[i] = pose.axis[i].dot(&joint_moment);
        }
        tau
    }

    /// Velocity and gravity torques `C(q, qd) qd + g(q)`: inverse dynamics at zero acceleration.
    pub fn bias(&self, pose: &Pose, qd: &Vector3<f64>) -> Vector3<f64> {
        self.inverse_dynamics(pose, qd, &Vector3::zeros())
    }

    /// The torques that hold the arm still against gravity, `g(q)`.
    pub fn gravity_torque(&self, pose: &Pose) -> Vector3<f64> {
        self.inverse_dynamics(pose, &Vector3::zeros(), &Vector3::zeros())
    }

    /// Forward dynamics: the accelerations that joint torques `tau` produce, from
    /// `M qdd = tau - C qd - g` with a 3x3 Cholesky solve.
    pub fn forward_dynamics(
        &self,
        pose: &Pose,
        qd: &Vector3<f64>,
        tau: &Vector3<f64>,
    ) -> Vector3<f64> {
        let rhs = tau - self.bias(pose, qd);
        self.mass_matrix(pose)
            .cholesky()
            // Every joint carries a body with inertia about its axis, so M is positive definite
            // for every q; only non-finite input can get here.
            .expect("the arm's mass matrix is positive definite for finite angles")
            .solve(&rhs)
    }

    /// Kinetic energy `1/2 qd^T M qd`, J.
    pub fn kinetic_energy(&self, pose: &Pose, qd: &Vector3<f64>) -> f64 {
        0.5 * qd.dot(&(self.mass_matrix(pose) * qd))
    }

    /// Potential energy of the centres of mass, zero at the base's height, J.
    pub fn potential_energy(&self, pose: &Pose) -> f64 {
        self.bodies
            .iter()
            .zip(&pose.com)
            .map(|(body, com)| body.mass * self.gravity * com.z)
            .sum()
    }
}

/// The inertia of a point mass at offset `d` about the origin of `d`: `m (|d|^2 1 - d d^T)`.
fn point_inertia(mass: f64, d: &Vector3<f64>) -> Matrix3<f64> {
    mass * (Matrix3::from_diagonal_element(d.norm_squared()) - d * d.transpose())
}

#[cfg(test)]
mod tests {
    use super::*;
    use hac_core::Rng;

    const G: f64 = 9.81;

    fn random_q(rng: &mut Rng) -> Vector3<f64> {
        Vector3::from_fn(|_, _| (rng.unit_f64() * 2.0 - 1.0) * std::f64::consts::PI)
    }

    fn random_vector(rng: &mut Rng, scale: f64) -> Vector3<f64> {
        Vector3::from_fn(|_, _| (rng.unit_f64() * 2.0 - 1.0) * scale)
    }

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol * (1.0 + a.abs().max(b.abs()))
    }

    #[test]
    fn zero_pose_matches_the_model_by_hand() {
        let arm = Ur5Arm::new(G);
        let pose = arm.pose(&Vector3::zeros());
        // At q = 0 the upper arm and forearm lie along +x, level with the lift axis.
        let lift_height = SHOULDER_HEIGHT;
        let expect = [
            (pose.origin(0), Vector3::new(0.0, 0.0, lift_height)),
            (pose.origin(1), Vector3::new(0.0, 0.13585, lift_height)),
            (pose.origin(2), Vector3::new(0.425, 0.01615, lift_height)),
            (pose.com(1), Vector3::new(0.28, 0.13585, lift_height)),
            (pose.com(2), Vector3::new(0.675, 0.01615, lift_height)),
            (pose.axis(0), Vector3::z()),
            (pose.axis(1), Vector3::y()),
            (pose.axis(2), Vector3::y()),
        ];
        for (got, want) in expect {
            assert!((got - want).norm() < 1e-6, "{got} vs {want}");
        }
    }

    /// The reference's own forward kinematics, written out in closed form: it turns about z by
    /// q1, then about y by q2 (x along the upper arm, 0.13585 to the side), then about y by q3
    /// at 0.425 along x, and puts the wrist at (0.39225, -0.1197, 0) in that last frame.
    fn reference_points(q: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
        let (s1, c1) = q[0].sin_cos();
        let (s2, c2) = q[1].sin_cos();
        let (s23, c23) = (q[1] + q[2]).sin_cos();
        let place = |reach: f64, side: f64, drop: f64| {
            Vector3::new(
                c1 * reach - s1 * side,
                s1 * reach + c1 * side,
                SHOULDER_HEIGHT - drop,
            )
        };
        let elbow = place(0.425 * c2, 0.13585, 0.425 * s2);
        let wrist = place(
            0.425 * c2 + 0.39225 * c23,
            0.13585 - 0.1197,
            0.425 * s2 + 0.39225 * s23,
        );
        (elbow, wrist)
    }

    #[test]
    fn goal_rule_points_match_the_reference_kinematics() {
        let arm = Ur5Arm::new(G);
        let mut rng = Rng::seed_from(1);
        for _ in 0..1000 {
            let q = random_q(&mut rng);
            let pose = arm.pose(&q);
            let (elbow, wrist) = reference_points(&q);
            let ours = pose.point(2, &WRIST_IN_FOREARM);
            assert!((ours - wrist).norm() < 1e-6, "{ours} vs {wrist}");
            // The reference's elbow sits 0.1197 m further out sideways; only heights matter.
            assert!((pose.elbow_height() - elbow.z).abs() < 1e-6);
            assert!((pose.wrist_height() - wrist.z).abs() < 1e-6);
        }
    }

    #[test]
    fn mass_matrix_is_symmetric_positive_definite() {
        let arm = Ur5Arm::new(G);
        let mut rng = Rng::seed_from(2);
        for _ in 0..1000 {
            let m = arm.mass_matrix(&arm.pose(&random_q(&mut rng)));
            assert_eq!(m, m.transpose());
            let eig = m.symmetric_eigenvalues();
            assert!(eig.min() > 1e-3, "{eig}");
        }
    }

    /// M is the derivative of the inverse dynamics with respect to the accelerations (which
    /// enter linearly, so central differences are exact up to rounding).
    #[test]
    fn mass_matrix_is_the_jacobian_of_inverse_dynamics() {
        let arm = Ur5Arm::new(G);
        let mut rng = Rng::seed_from(3);
        let h = 1e-3;
        for _ in 0..200 {
            let pose = arm.pose(&random_q(&mut rng));
            let qd = random_vector(&mut rng, 3.0);
            let qdd = random_vector(&mut rng, 10.0);
            let m = arm.mass_matrix(&pose);
            for col in 0..JOINTS {
                let mut step = Vector3::zeros();
                step[col] = h;
                let up = arm.inverse_dynamics(&pose, &qd, &(qdd + step));
                let down = arm.inverse_dynamics(&pose, &qd, &(qdd - step));
                let fd = (up - down) / (2.0 * h);
                for row in 0..JOINTS {
                    assert!(
                        close(fd[row], m[(row, col)], 1e-9),
                        "M[{row},{col}] {} vs {}",
                        m[(row, col)],
                        fd[row]
                    );
                }
            }
        }
    }

    #[test]
    fn gravity_torque_is_the_gradient_of_potential_energy() {
        let arm = Ur5Arm::new(G);
        let mut rng = Rng::seed_from(4);
        let h = 1e-6;
        for _ in 0..500 {
            let q = random_q(&mut rng);
            let g = arm.gravity_torque(&arm.pose(&q));
            for j in 0..JOINTS {
                let mut step = Vector3::zeros();
                step[j] = h;
                let fd = (arm.potential_energy(&arm.pose(&(q + step)))
                    - arm.potential_energy(&arm.pose(&(q - step))))
                    / (2.0 * h);
                assert!((g[j] - fd).abs() < 1e-7, "joint {j}: {} vs {fd}", g[j]);
            }
            // The pan axis is vertical: gravity never turns it.
            assert!(g[0].abs() < 1e-12);
        }
    }

    /// Kinetic energy from the bodies' own motion (`1/2 m v^2 + 1/2 w^T I w` at each centre of
    /// mass, velocities from the joint axes) equals `1/2 qd^T M qd`: M is built independently.
    #[test]
    fn kinetic_energy_matches_the_bodies_motion() {
        let arm = Ur5Arm::new(G);
        let mut rng = Rng::seed_from(5);
        for _ in 0..500 {
            let pose = arm.pose(&random_q(&mut rng));
            let qd = random_vector(&mut rng, 4.0);
            let mut by_bodies = 0.0;
            for i in 0..JOINTS {
                let mut omega = Vector3::zeros();
                let mut v = Vector3::zeros();
                for j in 0..=i {
                    let w = pose.axis(j) * qd[j];
                    omega += w;
                    v += w.cross(&(pose.com(i) - pose.origin(j)));
                }
                by_bodies += 0.5 * arm.mass(i) * v.norm_squared()
                    + 0.5 * omega.dot(&(pose.inertia[i] * omega));
            }
            let from_m = arm.kinetic_energy(&pose, &qd);
            assert!(close(by_bodies, from_m, 1e-12), "{by_bodies} vs {from_m}");
        }
    }

    /// Lagrange's equations fix the velocity terms: `C qd = Mdot qd - 1/2 d/dq (qd^T M qd)`,
    /// with `Mdot = sum_k dM/dq_k qd_k`. Both sides by central differences of M alone.
    #[test]
    fn velocity_torques_follow_from_the_mass_matrix() {
        let arm = Ur5Arm::new(0.0);
        let mut rng = Rng::seed_from(6);
        let h = 1e-5;
        for _ in 0..200 {
            let q = random_q(&mut rng);
            let qd = random_vector(&mut rng, 4.0);
            let dm = |k: usize| {
                let mut step = Vector3::zeros();
                step[k] = h;
                (arm.mass_matrix(&arm.pose(&(q + step))) - arm.mass_matrix(&arm.pose(&(q - step))))
                    / (2.0 * h)
            };
            let mut mdot = Matrix3::zeros();
            let mut grad = Vector3::zeros();
            for k in 0..JOINTS {
                let d = dm(k);
                mdot += d * qd[k];
                grad[k] = 0.5 * qd.dot(&(d * qd));
            }
            let lagrange = mdot * qd - grad;
            let rnea = arm.bias(&arm.pose(&q), &qd);
            for j in 0..JOINTS {
                assert!(
                    (rnea[j] - lagrange[j]).abs() < 1e-6,
                    "joint {j}: {} vs {}",
                    rnea[j],
                    lagrange[j]
                );
            }
        }
    }

    /// One classical Runge-Kutta step of the unforced arm.
    fn rk4(arm: &Ur5Arm, q: &mut Vector3<f64>, qd: &mut Vector3<f64>, dt: f64) {
        let accel = |q: &Vector3<f64>, qd: &Vector3<f64>| {
            arm.forward_dynamics(&arm.pose(q), qd, &Vector3::zeros())
        };
        let (q1, v1) = (*qd, accel(q, qd));
        let (q2, v2) = (
            *qd + 0.5 * dt * v1,
            accel(&(*q + 0.5 * dt * q1), &(*qd + 0.5 * dt * v1)),
        );
        let (q3, v3) = (
            *qd + 0.5 * dt * v2,
            accel(&(*q + 0.5 * dt * q2), &(*qd + 0.5 * dt * v2)),
        );
        let (q4, v4) = (*qd + dt * v3, accel(&(*q + dt * q3), &(*qd + dt * v3)));
        *q += dt / 6.0 * (q1 + 2.0 * q2 + 2.0 * q3 + q4);
        *qd += dt / 6.0 * (v1 + 2.0 * v2 + 2.0 * v3 + v4);
    }

    /// The model itself is conservative: integrated accurately, a 300 s tumble under gravity
    /// with no damping keeps its energy. Wrong velocity or gravity terms would show here.
    #[test]
    fn free_dynamics_conserve_energy() {
        let arm = Ur5Arm::new(G);
        let mut q = Vector3::new(0.3, -0.6, 0.9);
        let mut qd = Vector3::new(1.0, -2.0, 1.5);
        let energy = |q: &Vector3<f64>, qd: &Vector3<f64>| {
            let pose = arm.pose(q);
            arm.kinetic_energy(&pose, qd) + arm.potential_energy(&pose)
        };
        let e0 = energy(&q, &qd);
        let (mut worst, mut most_kinetic) = (0.0f64, 0.0f64);
        for _ in 0..150_000 {
            rk4(&arm, &mut q, &mut qd, 0.002);
            worst = worst.max((energy(&q, &qd) - e0).abs());
            most_kinetic = most_kinetic.max(arm.kinetic_energy(&arm.pose(&q), &qd));
        }
        // Observed: 1.5e-3 J out of up to 59 J of kinetic energy.
        assert!(most_kinetic > 30.0, "{most_kinetic}");
        assert!(worst < 1e-4 * most_kinetic, "energy error {worst} J");
    }

    /// Forward dynamics inverts inverse dynamics.
    #[test]
    fn forward_dynamics_inverts_inverse_dynamics() {
        let arm = Ur5Arm::new(G);
        let mut rng = Rng::seed_from(7);
        for _ in 0..500 {
            let pose = arm.pose(&random_q(&mut rng));
            let qd = random_vector(&mut rng, 4.0);
            let qdd = random_vector(&mut rng, 20.0);
            let tau = arm.inverse_dynamics(&pose, &qd, &qdd);
            let back = arm.forward_dynamics(&pose, &qd, &tau);
            assert!((back - qdd).norm() < 1e-9, "{back} vs {qdd}");
        }
    }
}
