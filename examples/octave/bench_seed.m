% Times the seed's simulation_quadrotor.m (truth, EKF and running mean over one run) under
% GNU Octave (run from this folder: RUNS=5 octave-cli --no-gui -q bench_seed.m): the P1 planar quadrotor, 1,001 samples (10 s at dt = 0.01), hover thrust.
rotor_data.m = 0.5; rotor_data.r = 0.15; rotor_data.I = 0.005; rotor_data.g = 9.81;
rotor_data.dt = 0.01;
rotor_data.C = [0 0 1 0 0 0; 0 0 0 0 1 0; 0 0 0 0 0 1];
rotor_data.A = zeros(6);
time = 0:0.01:10;
control_input = repmat([4.0, 4.0] * 0.5 * 9.81 / 4.0, length(time), 1);
noise_data.state_noise_amp = 0.003;
noise_data.output_noise_amp = 0.01;
x0 = [0 0 10 0 0 0];
randn('seed', 47);
runs = str2num(getenv('RUNS'));
simulation_quadrotor(rotor_data, control_input, noise_data, time, x0); % warm-up
% CPU time (cputime), not wall: the machine is shared.
c0 = cputime;
for i = 1:runs
  [s, o, e] = simulation_quadrotor(rotor_data, control_input, noise_data, time, x0);
end
el = cputime - c0;
printf('octave %d runs x %d samples (EKF + running mean): %.4f s CPU per run, %.0f ns CPU per step\n', runs, length(time), el / runs, el / runs / (length(time) - 1) * 1e9);
