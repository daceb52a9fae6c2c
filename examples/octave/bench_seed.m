% Times the seed's simulation_quadrotor.m (truth, EKF and running mean over one run) under
% GNU Octave: the P1 planar quadrotor, 1,001 samples (10 s at dt = 0.01), hover thrust.
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
t0 = tic;
for i = 1:runs
  [s, o, e] = simulation_quadrotor(rotor_data, control_input, noise_data, time, x0);
end
el = toc(t0);
printf('octave %d runs x %d samples: %.4f s per run, %.1f ns per step\n', runs, length(time), el / runs, el / runs / (length(time) - 1) * 1e9);
