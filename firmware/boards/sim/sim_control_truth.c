/* sim_control_truth.c - the control commands of the sensors: their truth (set, random, get),
 * injected faults, power cuts, flash counts, quit. */
#define _GNU_SOURCE
#include "sim_control_priv.h"

static int parse_accel_truth(req_t *q, int n, adxl355_truth_t *t, double st[3])
{
    const sj_doc_t *d = q->d;
    if (d->nodes[n].type != SJ_OBJ) {
        return ctl_fail("accel must be an object");
    }
    if (ctl_check_keys(q, n, "m,bias_mps2,noise_n,rw_k,bias_tc,scale_tc,bias_tc2,bias_tc3,hysteresis,"
                         "hysteresis_width_c,st_force_g") != 0) {
        return -1;
    }
    int k;
    if ((k = sj_get(d, n, "m")) >= 0 && ctl_node_mat3(d, k, "accel.m", t->m) != 0) {
        return -1;
    }
    static const char *names[] = {"bias_mps2", "noise_n", "rw_k", "bias_tc", "scale_tc", "bias_tc2",
                                  "bias_tc3", "hysteresis", "hysteresis_width_c", "st_force_g"};
    double *dst[] = {t->bias_mps2, t->noise_n, t->rw_k, t->bias_tc, t->scale_tc, t->bias_tc2,
                     t->bias_tc3, t->hysteresis, t->hysteresis_width_c, st};
    for (int i = 0; i < 10; i++) {
        if ((k = sj_get(d, n, names[i])) >= 0 && ctl_node_vec(d, k, names[i], dst[i], 3, 1) != 0) {
            return -1;
        }
    }
    for (int i = 0; i < 3; i++) {
        if (t->noise_n[i] < 0.0 || t->rw_k[i] < 0.0) {
            return ctl_fail("accel noise_n and rw_k must be >= 0");
        }
        if (!(t->hysteresis_width_c[i] >= 0.0 && t->hysteresis_width_c[i] <= 50.0)) {
            return ctl_fail("accel hysteresis_width_c must be in 0 .. 50 degC");
        }
    }
    return 0;
}

static int parse_gyro_truth(req_t *q, int n, sim_adxrs450_truth_t *t, const char *who)
{
    const sj_doc_t *d = q->d;
    if (ctl_is_null(d, n)) {
        return 0;
    }
    if (d->nodes[n].type != SJ_OBJ) {
        return ctl_fail("%s must be an object or null", who);
    }
    if (ctl_check_keys(q, n, "sens,bias_rad_s,noise_n,bias_rw_k,bias_instability_rad_s,bias_tempco_rad_s_per_c,"
                         "scale_tempco_per_c,gsens_rad_s_per_mps2,bias_tc2,bias_tc3,hysteresis,"
                         "hysteresis_width_c") != 0) {
        return -1;
    }
    int k;
    if ((k = sj_get(d, n, "sens")) >= 0 && ctl_node_vec(d, k, "sens", t->sens, 3, 0) != 0) {
        return -1;
    }
    if ((k = sj_get(d, n, "gsens_rad_s_per_mps2")) >= 0 &&
        ctl_node_vec(d, k, "gsens_rad_s_per_mps2", t->gsens_rad_s_per_mps2, 3, 0) != 0) {
        return -1;
    }
    static const char *names[] = {"bias_rad_s", "noise_n", "bias_rw_k", "bias_tempco_rad_s_per_c",
                                  "scale_tempco_per_c", "bias_tc2", "bias_tc3", "hysteresis",
                                  "hysteresis_width_c", "bias_instability_rad_s"};
    double *dst[] = {&t->bias_rad_s, &t->noise_n, &t->bias_rw_k, &t->bias_tempco_rad_s_per_c,
                     &t->scale_tempco_per_c, &t->bias_tc2, &t->bias_tc3, &t->hysteresis,
                     &t->hysteresis_width_c, &t->bias_instability_rad_s};
    for (int i = 0; i < 10; i++) {
        if ((k = sj_get(d, n, names[i])) >= 0 && ctl_node_num(d, k, names[i], dst[i]) != 0) {
            return -1;
        }
    }
    if (t->noise_n < 0.0 || t->bias_rw_k < 0.0 || t->bias_instability_rad_s < 0.0) {
        return ctl_fail("gyro noise_n, bias_rw_k and bias_instability_rad_s must be >= 0");
    }
    if (!(t->hysteresis_width_c >= 0.0 && t->hysteresis_width_c <= 50.0)) {
        return ctl_fail("gyro hysteresis_width_c must be in 0 .. 50 degC");
    }
    return 0;
}

int ctl_cmd_set_truth(req_t *q)
{
    sim_t *s = &g_sim;
    const sj_doc_t *d = q->d;
    if (ctl_check_keys(q, q->root, "cmd,id,accel,gyro") != 0) {
        return -1;
    }
    adxl355_truth_t at;
    adxl355_model_get_truth(&s->accel, &at);
    double st[3];
    memcpy(st, s->accel.st_force_g, sizeof st);
    sim_adxrs450_truth_t gt[3];
    for (int i = 0; i < 3; i++) {
        gt[i] = *sim_adxrs450_get_truth(&s->gyro[i]);
    }
    int an = sj_get(d, q->root, "accel"), gn = sj_get(d, q->root, "gyro");
    if (!ctl_is_null(d, an) && parse_accel_truth(q, an, &at, st) != 0) {
        return -1;
    }
    if (!ctl_is_null(d, gn)) {
        if (d->nodes[gn].type == SJ_ARR) {
            if (d->nodes[gn].count > 3) {
                return ctl_fail("gyro: at most 3 entries (x, y, z)");
            }
            for (int i = 0; i < d->nodes[gn].count; i++) {
                if (parse_gyro_truth(q, sj_at(d, gn, i), &gt[i], "gyro[i]") != 0) {
                    return -1;
                }
            }
        } else if (d->nodes[gn].type == SJ_OBJ) {
            if (ctl_check_keys(q, gn, "x,y,z") != 0) {
                return -1;
            }
            static const char *ax[] = {"x", "y", "z"};
            for (int i = 0; i < 3; i++) {
                if (parse_gyro_truth(q, sj_get(d, gn, ax[i]), &gt[i], ax[i]) != 0) {
                    return -1;
                }
            }
        } else {
            return ctl_fail("gyro must be a list of 3 objects or {x, y, z}");
        }
    }
    sim_models_sync(); /* the old truth holds up to now */
    adxl355_model_set_truth(&s->accel, &at);
    memcpy(s->accel.st_force_g, st, sizeof st);
    for (int i = 0; i < 3; i++) {
        sim_adxrs450_set_truth(&s->gyro[i], &gt[i]);
    }
    return 0;
}

int ctl_cmd_randomize_truth(req_t *q)
{
    double seed = (double)g_sim.seed;
    if (ctl_check_keys(q, q->root, "cmd,id,seed") != 0 || ctl_opt_num(q, q->root, "seed", &seed) < 0) {
        return -1;
    }
    if (seed < 0 || seed > 18446744073709549568.0 || seed != floor(seed)) {
        return ctl_fail("seed must be a non-negative integer");
    }
    sim_models_sync();
    sim_randomize_truth((uint64_t)seed);
    ctl_put_u64(q->r, "seed", (uint64_t)seed);
    return 0;
}

int ctl_cmd_get_truth(req_t *q)
{
    sim_t *s = &g_sim;
    sj_buf_t *r = q->r;
    if (ctl_check_keys(q, q->root, "cmd,id") != 0) {
        return -1;
    }
    /* Current true biases. The accelerometer can be advanced to now at no cost to its
     * noise sequence (it draws per output sample); a gyro draws its random walk per
     * advance, so it only gets the current world (temperature) at its own time. */
    sim_model_advance(IB_CS_ACCEL);
    sim_world_t w;
    sim_phys_specific_force(&s->phys, s->t_us, w.specific_force_mps2);
    sim_phys_omega(&s->phys, s->t_us, w.rate_rad_s);
    double die[SIM_DIES];
    for (int i = 0; i < SIM_DIES; i++) {
        die[i] = sim_thermal_die(&s->thermal, &s->phys, i, s->t_us);
    }

    ctl_put_u64(r, "time_us", s->t_us);
    adxl355_truth_t at;
    adxl355_model_get_truth(&s->accel, &at);
    double tb[3]; /* adxl355_model_true_bias() at the current temperature (the model only
                     takes the temperature when it advances, and time may not have moved) */
    for (int i = 0; i < 3; i++) {
        tb[i] = at.bias_mps2[i] + adxl355_truth_thermal_bias(&at, i, die[IB_CS_ACCEL], s->accel.hyst_h[i]) +
                s->accel.rw_bias[i];
    }
    sj_key(r, "accel");
    sj_raw(r, "{");
    sj_key(r, "m");
    sj_raw(r, "[");
    for (int i = 0; i < 3; i++) {
        if (i) {
            sj_raw(r, ", ");
        }
        sj_vec(r, at.m[i], 3);
    }
    sj_raw(r, "]");
    ctl_put_vec(r, "bias_mps2", at.bias_mps2, 3);
    ctl_put_vec(r, "noise_n", at.noise_n, 3);
    ctl_put_vec(r, "rw_k", at.rw_k, 3);
    ctl_put_vec(r, "bias_tc", at.bias_tc, 3);
    ctl_put_vec(r, "scale_tc", at.scale_tc, 3);
    ctl_put_vec(r, "bias_tc2", at.bias_tc2, 3);
    ctl_put_vec(r, "bias_tc3", at.bias_tc3, 3);
    ctl_put_vec(r, "hysteresis", at.hysteresis, 3);
    ctl_put_vec(r, "hysteresis_width_c", at.hysteresis_width_c, 3);
    ctl_put_vec(r, "hysteresis_branch", s->accel.hyst_h, 3);
    ctl_put_num(r, "die_temperature_c", die[IB_CS_ACCEL]);
    ctl_put_vec(r, "st_force_g", s->accel.st_force_g, 3);
    ctl_put_vec(r, "true_bias_mps2", tb, 3);
    ctl_put_vec(r, "rw_bias_mps2", s->accel.rw_bias, 3);
    ctl_put_bool(r, "missing", s->accel.fault.missing);
    sj_raw(r, "}");
    sj_key(r, "gyro");
    sj_raw(r, "[");
    for (int i = 0; i < 3; i++) {
        sim_adxrs450_t *m = &s->gyro[i];
        w.temperature_c = die[1 + i];
        sim_adxrs450_advance(m, m->t_us, &w); /* same time: only the world changes */
        const sim_adxrs450_truth_t *t = sim_adxrs450_get_truth(m);
        if (i) {
            sj_raw(r, ", ");
        }
        sj_raw(r, "{");
        ctl_put_u64(r, "axis", (uint64_t)m->axis);
        ctl_put_vec(r, "sens", t->sens, 3);
        ctl_put_num(r, "bias_rad_s", t->bias_rad_s);
        ctl_put_num(r, "noise_n", t->noise_n);
        ctl_put_num(r, "bias_rw_k", t->bias_rw_k);
        ctl_put_num(r, "bias_instability_rad_s", t->bias_instability_rad_s);
        ctl_put_num(r, "bias_tempco_rad_s_per_c", t->bias_tempco_rad_s_per_c);
        ctl_put_num(r, "scale_tempco_per_c", t->scale_tempco_per_c);
        ctl_put_vec(r, "gsens_rad_s_per_mps2", t->gsens_rad_s_per_mps2, 3);
        ctl_put_num(r, "bias_tc2", t->bias_tc2);
        ctl_put_num(r, "bias_tc3", t->bias_tc3);
        ctl_put_num(r, "hysteresis", t->hysteresis);
        ctl_put_num(r, "hysteresis_width_c", t->hysteresis_width_c);
        ctl_put_num(r, "hysteresis_branch", m->hyst_h);
        ctl_put_num(r, "die_temperature_c", die[1 + i]);
        ctl_put_num(r, "true_bias_rad_s", sim_adxrs450_true_bias_rad_s(m));
        ctl_put_num(r, "rw_bias_rad_s", m->bias_rw_rad_s);
        ctl_put_num(r, "bi_bias_rad_s", sim_adxrs450_flicker_bias_rad_s(m));
        ctl_put_u64(r, "serial", m->serial);
        ctl_put_bool(r, "missing", m->missing);
        ctl_put_u64(r, "persistent_faults", m->fault_persistent);
        sj_raw(r, "}");
    }
    sj_raw(r, "]");
    ctl_put_thermal(r);
    sj_key(r, "world");
    sj_raw(r, "{");
    ctl_put_world(r);
    sj_raw(r, "}");
    return 0;
}

int ctl_cmd_inject(req_t *q)
{
    sim_t *s = &g_sim;
    const sj_doc_t *d = q->d;
    int fn = sj_get(d, q->root, "fault");
    if (fn < 0 || d->nodes[fn].type != SJ_STR) {
        return ctl_fail("missing 'fault'");
    }
    const char *f = d->nodes[fn].str;
    double count = 0, bits = 0, mask = 1, prob = 0;
    int cs, on, persistent;
    if (!strcmp(f, "gyro_fault_bits")) {
        if (ctl_check_keys(q, q->root, "cmd,id,fault,sensor,bits,persistent") != 0 ||
            (cs = ctl_sensor_cs(q, q->root, 0)) < 0 || ctl_req_num(q, q->root, "bits", &bits) != 0 ||
            ctl_opt_bool(q, q->root, "persistent", 0, &persistent) != 0) {
            return -1;
        }
        if (bits < 0 || bits > 0xFFFF || bits != floor(bits) || ((unsigned)bits & ~SIM_ADXRS450_FAULT_ALL)) {
            return ctl_fail("bits must be FAULT register bits (mask 0x%03X)", SIM_ADXRS450_FAULT_ALL);
        }
        if (persistent) {
            sim_adxrs450_set_persistent_faults(&s->gyro[cs - 1], (uint16_t)bits);
        } else {
            sim_adxrs450_inject_faults(&s->gyro[cs - 1], (uint16_t)bits);
        }
    } else if (!strcmp(f, "gyro_parity")) {
        if (ctl_check_keys(q, q->root, "cmd,id,fault,sensor,count,mask") != 0 ||
            (cs = ctl_sensor_cs(q, q->root, 0)) < 0 || ctl_req_num(q, q->root, "count", &count) != 0 ||
            ctl_opt_num(q, q->root, "mask", &mask) < 0) {
            return -1;
        }
        if (count < 0 || count > 1e9 || mask < 0 || mask > 4294967295.0) {
            return ctl_fail("bad count or mask");
        }
        sim_adxrs450_corrupt_responses(&s->gyro[cs - 1], (uint32_t)count, (uint32_t)mask);
    } else if (!strcmp(f, "missing")) {
        if (ctl_check_keys(q, q->root, "cmd,id,fault,sensor,on") != 0 || (cs = ctl_sensor_cs(q, q->root, 1)) < 0 ||
            ctl_opt_bool(q, q->root, "on", 1, &on) != 0) {
            return -1;
        }
        if (cs == IB_CS_ACCEL) {
            adxl355_model_set_missing(&s->accel, on);
        } else {
            sim_adxrs450_set_missing(&s->gyro[cs - 1], on);
        }
    } else if (!strcmp(f, "spi_error")) {
        if (ctl_check_keys(q, q->root, "cmd,id,fault,sensor,count,probability") != 0 ||
            (cs = ctl_sensor_cs(q, q->root, 1)) < 0) {
            return -1;
        }
        int hc = ctl_opt_num(q, q->root, "count", &count), hp = ctl_opt_num(q, q->root, "probability", &prob);
        if (hc < 0 || hp < 0) {
            return -1;
        }
        if (!hc && !hp) {
            return ctl_fail("give count or probability");
        }
        if (count < 0 || count > 1e9 || prob < 0.0 || prob > 1.0) {
            return ctl_fail("count must be >= 0, probability in 0 .. 1");
        }
        if (hc) {
            s->spi_faults.error_count[cs] = (uint32_t)count;
        }
        if (hp) {
            s->spi_faults.error_prob[cs] = prob;
        }
    } else if (!strcmp(f, "link_drop") || !strcmp(f, "link_flip")) {
        if (ctl_check_keys(q, q->root, "cmd,id,fault,count") != 0 || ctl_req_num(q, q->root, "count", &count) != 0) {
            return -1;
        }
        if (count < 0 || count > 1e9) {
            return ctl_fail("count must be in 0 .. 1e9");
        }
        if (f[5] == 'd') {
            s->link.drop_remaining = (uint32_t)count;
        } else {
            s->link.flip_remaining = (uint32_t)count;
        }
    } else if (!strcmp(f, "accel_stuck") || !strcmp(f, "accel_shadow")) {
        if (ctl_check_keys(q, q->root, "cmd,id,fault,on") != 0 || ctl_opt_bool(q, q->root, "on", 1, &on) != 0) {
            return -1;
        }
        if (f[6] == 's' && f[7] == 't') {
            adxl355_model_set_stuck_data(&s->accel, on);
        } else {
            adxl355_model_set_shadow_corrupt(&s->accel, on);
        }
    } else if (!strcmp(f, "accel_wrong_id")) {
        /* a part that answers with another PARTID (0xEE instead of 0xED): a different or
         * counterfeit chip; takes effect at the driver's next probe (power cut / reboot) */
        if (ctl_check_keys(q, q->root, "cmd,id,fault,on") != 0 || ctl_opt_bool(q, q->root, "on", 1, &on) != 0) {
            return -1;
        }
        s->accel.id[2] = on ? 0xEE : 0xED;
    } else if (!strcmp(f, "clear")) {
        if (ctl_check_keys(q, q->root, "cmd,id,fault") != 0) {
            return -1;
        }
        s->accel.fault.missing = s->accel.fault.stuck_data = s->accel.fault.shadow_corrupt = 0;
        s->accel.id[2] = 0xED;
        for (int i = 0; i < 3; i++) {
            sim_adxrs450_set_persistent_faults(&s->gyro[i], 0);
            sim_adxrs450_corrupt_responses(&s->gyro[i], 0, 0);
            sim_adxrs450_set_missing(&s->gyro[i], 0);
        }
        memset(s->spi_faults.error_count, 0, sizeof s->spi_faults.error_count);
        memset(s->spi_faults.error_prob, 0, sizeof s->spi_faults.error_prob);
        s->link.drop_remaining = s->link.flip_remaining = 0;
        s->flash.cut_after = 0;
    } else {
        return ctl_fail("unknown fault '%s' (gyro_fault_bits, gyro_parity, missing, spi_error, "
                    "link_drop, link_flip, accel_stuck, accel_shadow, accel_wrong_id, clear)", f);
    }
    sj_key(q->r, "fault");
    sj_str(q->r, f);
    return 0;
}

int ctl_cmd_power_cut(req_t *q)
{
    sim_t *s = &g_sim;
    double n = 0;
    if (ctl_check_keys(q, q->root, "cmd,id,after_flash_ops") != 0 ||
        ctl_opt_num(q, q->root, "after_flash_ops", &n) < 0) {
        return -1;
    }
    if (n < 0 || n > 1e9 || n != floor(n)) {
        return ctl_fail("after_flash_ops must be a whole number >= 1 (or omitted for now)");
    }
    if (n == 0) {
        s->flash.cut_after = 0;
        sim_request_reset(SIM_RESET_POWER_CUT); /* outside the core: taken by the loop */
        sj_key(q->r, "when");
        sj_str(q->r, "now");
    } else {
        s->flash.cut_after = (int64_t)n;
        sj_key(q->r, "when");
        sj_printf(q->r, "\"during flash op %lld from now\"", (long long)n);
    }
    return 0;
}

int ctl_cmd_flash_ops(req_t *q)
{
    if (ctl_check_keys(q, q->root, "cmd,id") != 0) {
        return -1;
    }
    ctl_put_u64(q->r, "flash_ops", g_sim.flash.ops_since_boot);
    ctl_put_u64(q->r, "flash_ops_total", g_sim.flash.ops_total);
    ctl_put_u64(q->r, "power_cut_armed", (uint64_t)(g_sim.flash.cut_after > 0 ? g_sim.flash.cut_after : 0));
    ctl_put_u64(q->r, "power_cuts", g_sim.power_cuts);
    ctl_put_u64(q->r, "boots", g_sim.boots);
    return 0;
}

int ctl_cmd_quit(req_t *q)
{
    if (ctl_check_keys(q, q->root, "cmd,id") != 0) {
        return -1;
    }
    g_sim.quit = 1;
    return 0;
}
